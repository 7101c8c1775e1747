"""``executor=local``: one job after another in the driver's process."""

from __future__ import annotations

from pathlib import Path

from pipeline.data.scene import Scene
from pipeline.experiment.executors.base import OnDone, OnRound, scene_key
from pipeline.experiment.executors.worker import run_here
from pipeline.experiment.spec import Job


class LocalExecutor:
    slots = 1
    runs_here = True

    def __init__(self):
        self.running: list[Job] = []  # the jobs a stop signal interrupted (see SweepInterrupted)

    @classmethod
    def from_config(cls, cfg: dict, output_dir: Path) -> "LocalExecutor":
        return cls()

    def map(self, jobs: list[Job], scenes: dict[str, Scene], on_done: OnDone,
            on_round: OnRound | None = None) -> None:
        for job in jobs:
            report = None if on_round is None else (lambda message, job=job: on_round(job, message))
            self.running = [job]
            outcome = run_here(job, scenes.get(scene_key(job)), report)
            self.running = []
            on_done(job, outcome)
