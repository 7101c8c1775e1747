"""What the driver says on the console while a sweep runs: a line per finished job (done, running,
failed, with the sweep's ETA from the rounds heard so far), a line per round, the headline of a job's
outcome, the warning for a degraded final model."""

from __future__ import annotations

import json
from pathlib import Path

from pipeline.experiment.console import console
from pipeline.experiment.layout import JobFolder
from pipeline.experiment.outcome import TRACEBACK_ARTIFACT, JobOutcome, RoundMessage
from pipeline.experiment.spec import Job

LOG = console()


class Progress:
    """Jobs done / running / failed and an ETA, one line per finished job and per finished round.
    Before any job has finished the ETA comes from the rounds heard so far: the mean seconds of a
    round times the rounds left (each job's count of rounds as its messages say, the typical count
    for jobs not yet heard from), over the slots."""

    def __init__(self, name: str, total: int, slots: int):
        self.name, self.total, self.slots = name, total, max(1, slots)
        self.done = self.failed = 0
        self.job_seconds: list[float] = []
        self.round_seconds: list[float] = []
        self.rounds_of: dict[str, int] = {}     # config hash -> rounds the job has (its messages say)
        self.rounds_heard: dict[str, int] = {}  # config hash -> rounds heard so far
        self.finished_jobs: set[str] = set()

    def rounds_eta(self) -> float | None:
        """Seconds left from the rounds heard so far (None before the first round)."""
        if not self.round_seconds or not self.rounds_of:
            return None
        typical = sorted(self.rounds_of.values())[len(self.rounds_of) // 2]
        unheard = self.total - len(self.finished_jobs) - len(set(self.rounds_of) - self.finished_jobs)
        left = sum(max(0, n - self.rounds_heard.get(h, 0)) for h, n in self.rounds_of.items()
                   if h not in self.finished_jobs) + max(0, unheard) * typical
        return sum(self.round_seconds) / len(self.round_seconds) * left / self.slots

    def update(self, job: Job, outcome: JobOutcome) -> None:
        self.finished_jobs.add(job.config_hash)
        self.done += 1
        self.failed += not outcome.finished
        left = self.total - self.done
        self.job_seconds.append(outcome.seconds or 0.0)
        eta = sum(self.job_seconds) / len(self.job_seconds) * left / self.slots  # jobs alike, slots full
        running = min(left, self.slots)
        LOG.info(f"[{self.name}] {self.done}/{self.total} done, {running} running, {self.failed} failed, "
                 f"ETA {eta / 60:.1f} min | {job.label}: {outcome.status} "
                 f"{_headline(outcome, job)}")
        self.degraded(job, outcome)

    def round(self, job: Job, message: RoundMessage) -> None:
        """One line per finished round of a running job."""
        rec = message.record
        self.round_seconds.append(message.seconds)
        self.rounds_of[job.config_hash] = message.rounds
        self.rounds_heard[job.config_hash] = rec.round + 1
        eta = self.rounds_eta()
        what = "final" if message.final else f"round {rec.round + 1}/{message.rounds}"
        on = f"{message.curve_views} test views" if message.curve_views else "the curve's test views"
        LOG.info(f"[{self.name}] {job.label}: {what}, {rec.num_views} views, "
                 f"curve PSNR {rec.test_psnr:.2f} dB (on {on}), {message.seconds:.0f} s"
                 + (f" | sweep ETA {eta / 60:.1f} min (from the rounds so far)" if eta is not None else ""))

    def degraded(self, job: Job, outcome: JobOutcome) -> None:
        final = outcome.final
        if final is not None and final.degraded:
            LOG.warning(f"[{self.name}] warning: {job.label} ended on a degraded model: final PSNR "
                        f"{final.curve_psnr_drop:.2f} dB below its last round on the same views "
                        "(flagged in the records, MLflow tag degraded=true)")


def _headline(outcome: JobOutcome, job: Job) -> str:
    if not outcome.finished:  # the error's last line, and where its whole traceback is
        last = next((ln.strip() for ln in reversed(outcome.traceback.splitlines()) if ln.strip()), "?")
        path = JobFolder(Path(job.execution.job_dir if job.execution is not None else ".")).artifacts / TRACEBACK_ARTIFACT
        return f"after {outcome.attempts} attempt(s): {last[:300]} (traceback: {path})"
    if outcome.final is not None:
        return (f"test PSNR {outcome.final.psnr:.2f} dB (all {outcome.final.test_views} test views) in "
                f"{outcome.seconds or 0:.0f} s")
    ause = outcome.uncertainty.ause if outcome.uncertainty is not None else {}
    return f"AUSE {json.dumps({k: round(v, 3) for k, v in ause.items()})}"
