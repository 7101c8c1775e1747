"""``executor=slurm``: one SLURM job array per sweep, through submitit (what Hydra's submitit
launcher uses), with ``executor.cluster=local`` running the same code without SLURM (submitit's
local executor: every job a process on this machine; for tests and dry runs).

Each array task runs ``worker.run_here`` for one job (``SlurmJobRunner``), reading the scene from
its path (the data, ``output_dir`` and the venv must be on a filesystem the compute nodes share).
On preemption or timeout SLURM signals the task, submitit requeues it (``max_requeues`` times) and
the job resumes from its last round checkpoint in its folder. Round messages go to the job folder's
``progress.jsonl``, which the driver tails while it polls the array; submitit's own logs and
pickles are under ``<output_dir>/slurm/``.
"""

from __future__ import annotations

import base64
import json
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path

from pipeline.data.scene import Scene
from pipeline.experiment.episode_settings import ConfigError
from pipeline.experiment.executors.base import OnDone, OnRound
from pipeline.experiment.executors.worker import DriverIdentity, read_starts, run_here
from pipeline.experiment.interrupt import SweepInterrupted, critical
from pipeline.experiment.layout import JobFolder
from pipeline.experiment.outcome import JobOutcome, RoundMessage, StepProgress, message_from_dict
from pipeline.experiment.spec import Job

POLL_SECONDS = 2.0


def _checkpointable():
    try:
        from submitit.helpers import Checkpointable
    except ImportError:
        return object
    return Checkpointable


def message_line(message: RoundMessage | StepProgress) -> str:
    data = message.to_dict()
    if "images" in data:
        data["images"] = {k: base64.b64encode(v).decode() for k, v in data["images"].items()}
    return json.dumps(data)


def message_of(line: str) -> RoundMessage | StepProgress:
    data = json.loads(line)
    if "images" in data:
        data["images"] = {k: base64.b64decode(v) for k, v in data["images"].items()}
    return message_from_dict(data)


def unheard_rounds(outcome: JobOutcome, heard: set[int]) -> list[RoundMessage]:
    """The rounds of a finished job that never reached the driver as a progress line: a task
    preempted after a round's checkpoint and before its line resumes past that round, so the round
    is said from the job's result instead (its images, if any, are not kept)."""
    episode = outcome.episode
    if episode is None:
        return []
    return [RoundMessage.of(r, len(episode.rounds)) for r in episode.rounds if r.round not in heard]


class SlurmJobRunner(_checkpointable()):
    """One array task: run the job here; requeued as is (submitit's ``Checkpointable``: the job's
    own round checkpoints carry its state)."""

    def __init__(self, expected: dict):
        self.expected = expected

    def __call__(self, plain_job: dict) -> dict:
        job = Job.from_dict(plain_job)
        progress = JobFolder(Path(job.execution.job_dir)).progress_file

        def report(message: RoundMessage) -> None:
            progress.parent.mkdir(parents=True, exist_ok=True)
            with open(progress, "a") as f:
                f.write(message_line(message) + "\n")
        return run_here(job, None, report, DriverIdentity(**self.expected)).to_dict()


@dataclass
class ProgressTail:
    """The lines a job's ``progress.jsonl`` gained since the last look (complete lines only)."""

    path: Path
    offset: int = 0
    partial: str = field(default="")

    @classmethod
    def at_end(cls, path: Path) -> "ProgressTail":
        return cls(path, path.stat().st_size if path.exists() else 0)

    def new_lines(self) -> list[str]:
        if not self.path.exists():
            return []
        with open(self.path) as f:
            f.seek(self.offset)
            text = f.read()
            self.offset = f.tell()
        text, self.partial = self.partial + text, ""
        lines = text.split("\n")
        self.partial = lines.pop()  # "" after a complete line
        return [ln for ln in lines if ln]


def died(job: Job, error: str, paths=None) -> JobOutcome:
    """The outcome of a task that ended without returning one (killed, out of memory, out of
    requeues): its attempts are the starts its job folder recorded (``starts.jsonl``), and where it
    last ran is kept as the worker, so the record says how often it began and on which node."""
    starts = read_starts(Path(job.execution.job_dir))
    where = f"\nsubmitit logs: {paths.stdout} {paths.stderr}" if paths is not None else ""
    said = (f"\nthe task ended without a result after {len(starts)} start(s), the last on {starts[-1]['host']} "
            f"({starts[-1]['node']})" if starts else "\nthe task ended before the job started (no start recorded)")
    outcome = JobOutcome.failed(max(1, len(starts)), [error + said + where])
    if starts:
        outcome.worker = {"host": starts[-1]["host"], "node": starts[-1]["node"], "pid": starts[-1].get("pid"),
                          "starts": len(starts), "first_started": starts[0]["started"], "ended": time.time()}
    return outcome


class SlurmExecutor:
    def __init__(self, output_dir: Path, cluster: str | None = None, partition: str | None = None,
                 account: str | None = None, timeout_min: int = 240, array_parallelism: int = 64,
                 max_requeues: int = 3, gpus_per_job: int = 0, mem_gb: float | None = None,
                 setup: list[str] | None = None, signal_delay_s: int | None = None):
        self.output_dir = Path(output_dir).resolve()
        self.cluster, self.partition, self.account = cluster, partition, account
        self.timeout_min, self.array_parallelism = timeout_min, array_parallelism
        self.max_requeues, self.gpus_per_job, self.mem_gb = max_requeues, gpus_per_job, mem_gb
        self.setup = list(setup or [])
        self.signal_delay_s = signal_delay_s  # how long before the time limit the task is told to requeue
        self.slots = 1
        self.running: list[Job] = []
        self.runs_here = cluster == "local"  # submitit's local executor: processes on this machine
        self.submitted: dict[str, object] = {}  # config hash -> submitit job (tests interrupt one)

    @classmethod
    def from_config(cls, cfg: dict, output_dir: Path) -> "SlurmExecutor":
        keys = ("cluster", "partition", "account", "timeout_min", "array_parallelism", "max_requeues",
                "gpus_per_job", "mem_gb", "setup", "signal_delay_s")
        return cls(output_dir, **{k: cfg[k] for k in keys if cfg.get(k) is not None})

    def _executor(self, jobs: list[Job]):
        try:
            import submitit
        except ImportError:
            raise ConfigError("executor=slurm needs submitit: pip install 'gopre[cluster]'") from None
        folder = self.output_dir / "slurm" / "%j"
        if self.cluster == "local":  # every task a process here; requeued at timeout as on SLURM
            ex = submitit.LocalExecutor(folder, max_num_timeout=self.max_requeues)
            params = {"timeout_min": self.timeout_min}
            if self.signal_delay_s is not None:
                params["signal_delay_s"] = self.signal_delay_s
            ex.update_parameters(**params)
        else:
            ex = submitit.AutoExecutor(folder=folder, cluster=self.cluster, slurm_max_num_timeout=self.max_requeues)
            if ex.cluster != "slurm":
                raise ConfigError("executor.cluster: no SLURM here (sbatch not found); executor.cluster=local "
                                  "runs the array on this machine")
            ex.update_parameters(**self._slurm_parameters(jobs))
        self.slots = len(jobs) if self.cluster == "local" else min(len(jobs), self.array_parallelism)
        return ex

    def _slurm_parameters(self, jobs: list[Job]) -> dict:
        """sbatch settings through submitit's AutoExecutor (generic names, else ``slurm_``)."""
        params = {"timeout_min": self.timeout_min, "cpus_per_task": max(j.execution.threads for j in jobs),
                  "name": jobs[0].sweep, "slurm_array_parallelism": self.array_parallelism}
        optional = {"gpus_per_node": self.gpus_per_job, "mem_gb": self.mem_gb, "slurm_partition": self.partition,
                    "slurm_account": self.account, "slurm_setup": self.setup,
                    "slurm_signal_delay_s": self.signal_delay_s}
        params.update({k: v for k, v in optional.items() if v})
        return params

    def map(self, jobs: list[Job], scenes: dict[str, Scene], on_done: OnDone,
            on_round: OnRound | None = None) -> None:
        if not jobs:
            return
        ex = self._executor(jobs)
        tails = {j.config_hash: ProgressTail.at_end(JobFolder(Path(j.execution.job_dir)).progress_file)
                 for j in jobs}
        runner = SlurmJobRunner(DriverIdentity.here().to_dict())
        with critical():
            array = ex.map_array(runner, [j.to_dict() for j in jobs])  # one job array per sweep
        pending = {j.config_hash: (j, s) for j, s in zip(jobs, array)}
        self.submitted = {h: s for h, (_, s) in pending.items()}
        heard: dict[str, set[int]] = {h: set() for h in pending}

        def hear(job: Job) -> None:
            for line in tails[job.config_hash].new_lines():
                message = message_of(line)
                if isinstance(message, RoundMessage):
                    heard[job.config_hash].add(message.record.round)
                on_round(job, message)
        try:
            while pending:
                for config_hash, (job, submitted) in list(pending.items()):
                    if on_round is not None:
                        hear(job)
                    if not submitted.done():
                        continue
                    del pending[config_hash]
                    outcome = self._outcome(submitted, job)
                    if on_round is not None:
                        hear(job)  # lines written after the last look
                        for message in unheard_rounds(outcome, heard[config_hash]):
                            on_round(job, message)
                    on_done(job, outcome)
                if pending:
                    time.sleep(POLL_SECONDS)
        except SweepInterrupted:
            self.running = []
            for job, submitted in pending.values():
                try:
                    submitted.cancel(check=False)
                except Exception:  # already ended
                    pass
                if Path(job.execution.job_dir).exists():
                    self.running.append(job)
            raise

    def _outcome(self, submitted, job: Job) -> JobOutcome:
        try:
            return JobOutcome.from_dict(submitted.result())
        except Exception:  # the task died (killed, out of memory, out of requeues): its logs say why
            return died(job, traceback.format_exc(), getattr(submitted, "paths", None))
