"""Executors: where a sweep's jobs run. One boundary (``Executor``), three implementations:

- ``local``: one job after another in the driver's process;
- ``ray``: one Ray task per job on a local Ray or a running cluster (``ray_cluster``);
- ``slurm``: one SLURM job array per sweep through submitit (``slurm``), requeued on preemption.

Each is its section in ``config`` (registered by kind) and its class. All three run
``worker.run_here`` for a job, so they give the same numbers at the same seed, and
a job's state (checkpoints, log, start list) lives in its folder under the sweep's ``output_dir``
wherever it runs: a job retried or requeued on another machine resumes from its last round.
"""

from __future__ import annotations

from pipeline.experiment.executors.base import Executor, OnDone, OnRound, scene_key
from pipeline.experiment.executors.config import SECTIONS, make_executor

__all__ = ["Executor", "OnDone", "OnRound", "make_executor", "scene_key", "EXECUTOR_KINDS"]

EXECUTOR_KINDS = tuple(SECTIONS)  # the registered kinds (``executors.config``)
