"""The boundary every executor implements, and what they share."""

from __future__ import annotations

from typing import Callable, Protocol, runtime_checkable

from pipeline.data.scene import Scene
from pipeline.experiment.outcome import JobOutcome, RoundMessage
from pipeline.experiment.spec import Job

OnDone = Callable[[Job, JobOutcome], None]
OnRound = Callable[[Job, RoundMessage], None]


@runtime_checkable
class Executor(Protocol):
    """Runs jobs and hands each outcome to the driver as soon as it is ready.

    ``map`` calls ``on_done(job, outcome)`` once per job (a FAILED outcome when the job could not
    finish, never an exception for an application error) and ``on_round(job, message)`` for each
    finished round it hears while jobs run; a stop signal (``SweepInterrupted``) cancels what
    runs and leaves the interrupted jobs in ``running``. ``slots``: jobs that run at once (the ETA).
    ``runs_here``: the jobs run on this machine (its CPU and its kernel cache)."""

    slots: int
    running: list[Job]
    runs_here: bool

    def map(self, jobs: list[Job], scenes: dict[str, Scene], on_done: OnDone,
            on_round: OnRound | None = None) -> None: ...


def scene_key(job: Job) -> str:
    """Jobs that read the same scene at the same resolution share one loaded ``Scene``."""
    return f"{job.scene_path}@{job.splat.get('image_width')}/{job.splat['preset']}" + ("+masks" if job.masks else "")
