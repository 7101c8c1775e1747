"""Each executor's ``executor`` section, registered by its kind with the class that runs it.

An executor is two things: its section here (a typed dataclass: the keys, their bounds and
defaults, which the schema checks and documents, and how many jobs it runs at once, which
``plan=true`` estimates with) and its class (``target``, imported only when a sweep uses it, so
reading a config never imports Ray or submitit). Its ``conf/executor/<kind>.yaml`` lists the same
defaults (a test keeps the two equal). As Hydra's submitit launcher declares its configs beside one
another and names the class each one builds.
"""

from __future__ import annotations

import importlib
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, ClassVar

from pipeline.bounds import FLOAT, INT, STR, bounded

SECTIONS: dict[str, Any] = {}  # kind -> its section dataclass (a class), in registration order


def executor(kind: str, target: str) -> Callable[[type], type]:
    """Register the section dataclass of ``kind``, run by ``target`` ("module:Class", a class with
    ``from_config(section: dict, output_dir) -> Executor``)."""
    def register(section: type) -> type:
        if kind in SECTIONS:
            raise ValueError(f"executor kind {kind!r} is registered twice")
        setattr(section, "target", target)
        SECTIONS[kind] = section
        return section
    return register


def executor_class(kind: str):
    """The class that runs ``kind`` (imported now)."""
    if kind not in SECTIONS:
        raise ValueError(f"executor.kind: must be one of {', '.join(SECTIONS)}, got {kind!r}")
    module, name = SECTIONS[kind].target.split(":")
    return getattr(importlib.import_module(module), name)


def planned_slots(cfg: dict, threads: list[int]) -> int:
    """How many jobs of these ``threads`` the executor of ``cfg`` runs at once (for the estimate)."""
    section = SECTIONS.get(str(cfg.get("kind")))
    return section.slots(cfg, threads) if section is not None and threads else 1


@executor("local", "pipeline.experiment.executors.local:LocalExecutor")
@dataclass(frozen=True)
class LocalExecutorSection:
    """One job after another in the driver's process."""

    target: ClassVar[str]
    kind: str = bounded("local", STR, choices=("local",))

    @staticmethod
    def slots(cfg: dict, threads: list[int]) -> int:
        return 1


@executor("ray", "pipeline.experiment.executors.ray_cluster:RayExecutor")
@dataclass(frozen=True)
class RayExecutorSection:
    """One Ray task per job, on a Ray this launch starts or a running cluster (``address``)."""

    target: ClassVar[str]
    kind: str = bounded("ray", STR, choices=("ray",))
    address: str | None = bounded(None, STR, nullable=True)
    num_cpus: int | None = bounded(None, INT, ge=1, nullable=True)
    gpus_per_job: float = bounded(0, FLOAT, ge=0)
    max_retries: int = bounded(2, INT, ge=0, le=100)

    @staticmethod
    def slots(cfg: dict, threads: list[int]) -> int:
        """The CPUs Ray gets over the fewest threads a job asks for."""
        cpus = cfg.get("num_cpus") or os.cpu_count() or 1
        return max(1, int(cpus) // max(1, min(threads)))


@executor("slurm", "pipeline.experiment.executors.slurm:SlurmExecutor")
@dataclass(frozen=True)
class SlurmExecutorSection:
    """One SLURM job array per sweep through submitit (``cluster: local``: its local executor)."""

    target: ClassVar[str]
    kind: str = bounded("slurm", STR, choices=("slurm",))
    cluster: str | None = bounded(None, STR, choices=("slurm", "local"), nullable=True)
    partition: str | None = bounded(None, STR, nullable=True)
    account: str | None = bounded(None, STR, nullable=True)
    timeout_min: int = bounded(240, INT, ge=1)
    array_parallelism: int = bounded(64, INT, ge=1)
    max_requeues: int = bounded(3, INT, ge=0, le=1000)
    gpus_per_job: int = bounded(0, INT, ge=0)
    mem_gb: float | None = bounded(None, FLOAT, gt=0, nullable=True)
    signal_delay_s: int | None = bounded(None, INT, ge=0, nullable=True)

    @staticmethod
    def slots(cfg: dict, threads: list[int]) -> int:
        return 1


def make_executor(cfg: dict, output_dir: Path):
    """The executor of ``executor.kind`` (the config group ``conf/executor``)."""
    return executor_class(str(cfg.get("kind"))).from_config(cfg, Path(output_dir))
