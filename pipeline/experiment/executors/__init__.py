"""Executors: where a sweep's jobs run. One boundary (``Executor``), three implementations:

- ``local``: one job after another in the driver's process;
- ``ray``: one Ray task per job on a local Ray or a running cluster (``ray_cluster``);
- ``slurm``: one SLURM job array per sweep through submitit (``slurm``), requeued on preemption.

All three run ``worker.run_here`` for a job, so they give the same numbers at the same seed, and
a job's state (checkpoints, log, start list) lives in its folder under the sweep's ``output_dir``
wherever it runs: a job retried or requeued on another machine resumes from its last round.
"""

from __future__ import annotations

from pathlib import Path

from pipeline.experiment.executors.base import Executor, OnDone, OnRound, scene_key

__all__ = ["Executor", "OnDone", "OnRound", "make_executor", "scene_key", "EXECUTOR_KINDS"]

EXECUTOR_KINDS = ("local", "ray", "slurm")


def make_executor(cfg: dict, output_dir: Path) -> Executor:
    """The executor of ``executor.kind`` (the config group ``conf/executor``)."""
    kind = cfg.get("kind")
    if kind == "local":
        from pipeline.experiment.executors.local import LocalExecutor
        return LocalExecutor()
    if kind == "ray":
        from pipeline.experiment.executors.ray_cluster import RayExecutor
        return RayExecutor(cfg.get("address"), cfg.get("num_cpus"), cfg.get("gpus_per_job", 0),
                           cfg.get("max_retries", 2), Path(output_dir))
    if kind == "slurm":
        from pipeline.experiment.executors.slurm import SlurmExecutor
        return SlurmExecutor.from_config(cfg, Path(output_dir))
    raise ValueError(f"executor.kind: must be one of {', '.join(EXECUTOR_KINDS)}, got {kind!r}")
