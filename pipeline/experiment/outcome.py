"""What one job ended with, and what it says while it runs: the typed records every room after
the worker reads.

A worker returns a ``JobOutcome``; across Ray it travels as ``to_dict()`` (plain data) and the
driver reads it back with ``from_dict``. The executors, the sweep driver, the records and the
tracker read attributes, not string keys, and a FAILED outcome is built in one place
(``JobOutcome.failed``) whether the retries ran out or the worker process died.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace

from pipeline.interchange.results import EpisodeResult, FinalMetrics, RoundRecord, UncertaintyResult

FINISHED, FAILED = "FINISHED", "FAILED"
TRACEBACK_ARTIFACT = "traceback.txt"


@dataclass
class JobOutcome:
    """status FINISHED or FAILED; attempts made; errors: the traceback of each failed attempt;
    result: the job's result dict (``EpisodeResult.to_dict()`` or the uncertainty experiment's;
    None when FAILED); artifacts: file name -> bytes for the tracker; seconds: the last
    attempt's wall time (None when not measured, e.g. a FAILED or a resumed outcome); worker:
    where and under what the job ran (``executors.worker.run_here``: host, node, pid, code
    version, packages, CPU, starts, first_started, ended; empty when not run by an executor)."""

    status: str
    attempts: int = 1
    errors: list[str] = field(default_factory=list)
    result: dict | None = None
    artifacts: dict[str, bytes] = field(default_factory=dict)
    seconds: float | None = None
    worker: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.status not in (FINISHED, FAILED):
            raise ValueError(f"JobOutcome status must be {FINISHED} or {FAILED}, got {self.status!r}")
        if self.status == FINISHED and self.result is None:
            raise ValueError("a FINISHED JobOutcome needs its result")

    @classmethod
    def failed(cls, attempts: int, errors: list[str]) -> "JobOutcome":
        """The one FAILED outcome: the last traceback also as the artifact ``traceback.txt``."""
        if not errors:
            raise ValueError("JobOutcome.failed needs the traceback of at least one attempt")
        return cls(FAILED, attempts, list(errors), None,
                   {TRACEBACK_ARTIFACT: errors[-1].encode()})

    @property
    def finished(self) -> bool:
        return self.status == FINISHED

    @property
    def traceback(self) -> str:
        """The last attempt's traceback ('' when no attempt failed)."""
        return self.errors[-1] if self.errors else ""

    @property
    def episode(self) -> EpisodeResult | None:
        """The typed episode result (None for a FAILED outcome or an uncertainty job's result)."""
        if self.result is None or "rounds" not in self.result:
            return None
        return EpisodeResult.from_dict(self.result)

    @property
    def uncertainty(self) -> UncertaintyResult | None:
        """The typed uncertainty-experiment result (None for a FAILED outcome or an episode)."""
        if self.result is None or "curves" not in self.result:
            return None
        return UncertaintyResult.from_dict(self.result)

    @property
    def final(self) -> FinalMetrics | None:
        """The episode's final metrics (None for a FAILED outcome or an uncertainty job)."""
        episode = self.episode
        return episode.final if episode is not None else None

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> "JobOutcome":
        unknown = set(data) - set(cls.__dataclass_fields__)
        if unknown:
            raise ValueError(f"JobOutcome.from_dict: unknown keys {sorted(unknown)}")
        return cls(**data)


@dataclass
class StepProgress:
    """Progress inside a round of a running job, said every ``job.progress_seconds``: the round
    (from 0; the final training is the last), its training steps done of its total (``phase``
    "training") or the views of a selection's Fisher pass done of its views ("fisher"), and the seconds
    since the job (this attempt) began. Travels as ``to_dict()`` beside the round messages."""

    round: int
    rounds: int
    done: int
    total: int
    seconds: float
    phase: str = "training"  # training steps, or "fisher": views of a selection's Fisher pass

    def text(self) -> str:
        what = "final training" if self.round + 1 == self.rounds else f"round {self.round + 1}/{self.rounds}"
        doing = (f"training step {self.done}/{self.total}" if self.phase == "training" else
                 f"selection, Fisher of {self.done}/{self.total} views")
        return f"{what}: {doing} ({self.seconds:.0f} s into the job)"

    def to_dict(self) -> dict:
        return {"progress": asdict(self)}


def message_from_dict(data: dict) -> "RoundMessage | StepProgress":
    """A message from a running job, either kind, from its ``to_dict()``."""
    if "progress" in data:
        return StepProgress(**data["progress"])
    return RoundMessage.from_dict(data)


@dataclass
class RoundMessage:
    """What the driver hears of one finished round of a running job: the round's record (the
    per-candidate scores and probe ids left out), how many rounds the job has (selection rounds +
    the final evaluation) and the round's images (name -> PNG bytes, when asked for). ``round``
    counts from 0, as in the records. Across Ray it travels as ``to_dict()``."""

    record: RoundRecord
    rounds: int
    images: dict[str, bytes] = field(default_factory=dict)
    job_started: float | None = None  # when the job (this attempt) began, seconds since the epoch
    curve_views: int | None = None    # how many test views the round's (curve) PSNR is over

    @classmethod
    def of(cls, record: RoundRecord, rounds: int) -> "RoundMessage":
        light = replace(record, scores={}, probes=[])
        return cls(light, rounds)

    @property
    def final(self) -> bool:
        """This is the job's final evaluation (no selection after it)."""
        return self.record.round + 1 == self.rounds

    @property
    def seconds(self) -> float:
        """Training + selection of this round."""
        return round(self.record.train_seconds + self.record.selection_seconds, 2)

    def to_dict(self) -> dict:
        return {"record": asdict(self.record), "rounds": self.rounds, "images": dict(self.images),
                "job_started": self.job_started, "curve_views": self.curve_views}

    @classmethod
    def from_dict(cls, data: dict) -> "RoundMessage":
        return cls(RoundRecord.from_dict(data["record"]), int(data["rounds"]), dict(data.get("images") or {}),
                   data.get("job_started"), data.get("curve_views"))
