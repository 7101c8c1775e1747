"""Executors: run jobs and hand each outcome to the driver as soon as it is ready.

``local`` runs jobs one after another in this process. ``ray`` runs one Ray task per job on a
local Ray (started with this machine's cores) or a running cluster (``address``); each task
reserves ``execution.threads`` CPUs (and ``gpus_per_job`` GPUs), scenes go into the object store
once per (scene, resolution), and results are collected with ``ray.wait`` as they finish. Both
call the same ``run_with_retries``, so they give the same numbers at the same seed.
"""

from __future__ import annotations

import os
import traceback
from typing import Callable

from pipeline.data.scene import Scene
from pipeline.experiment.job import run_with_retries

OnDone = Callable[[dict, dict], None]


class LocalExecutor:
    slots = 1

    def map(self, jobs: list[dict], scenes: dict[str, Scene], on_done: OnDone) -> None:
        for job in jobs:
            on_done(job, run_with_retries(job, scenes.get(scene_key(job))))


def scene_key(job: dict) -> str:
    return f"{job['scene_path']}@{job['splat'].get('image_width')}/{job['splat']['preset']}"


def _remote_run(job: dict, scene: Scene | None) -> dict:
    return run_with_retries(job, scene)


class RayExecutor:
    def __init__(self, address: str | None = None, num_cpus: int | None = None, gpus_per_job: float = 0,
                 max_retries: int = 2):
        self.address, self.num_cpus = address, num_cpus
        self.gpus_per_job, self.max_retries = gpus_per_job, max_retries
        self.slots = 1

    def _start(self):
        """Ray, and whether this call started it (then ``map`` shuts it down again)."""
        import ray

        if ray.is_initialized():  # e.g. a test session's shared Ray
            return ray, False
        if self.address:
            ray.init(address=self.address, include_dashboard=False, log_to_driver=False)
        else:
            # address="local": always a fresh local instance, never a stale cluster address file
            ray.init(address="local", num_cpus=self.num_cpus or os.cpu_count(), include_dashboard=False,
                     log_to_driver=False)
        return ray, True

    def map(self, jobs: list[dict], scenes: dict[str, Scene], on_done: OnDone) -> None:
        ray, started_here = self._start()
        try:
            refs = {key: ray.put(scene) for key, scene in scenes.items()}  # once per scene
            cpus = ray.cluster_resources().get("CPU", 1)
            self.slots = max(1, int(cpus // max(1, min(j["execution"]["threads"] for j in jobs)))) if jobs else 1
            task = ray.remote(_remote_run)
            pending = {}
            for job in jobs:
                options = {"num_cpus": job["execution"]["threads"], "num_gpus": self.gpus_per_job,
                           "max_retries": self.max_retries, "name": f"{job['method']}:{job['scene']}"}
                pending[task.options(**options).remote(job, refs.get(scene_key(job)))] = job
            while pending:
                done, _ = ray.wait(list(pending), num_returns=1)
                job = pending.pop(done[0])
                try:
                    outcome = ray.get(done[0])
                except Exception:  # the worker died more often than max_retries allows
                    tb = traceback.format_exc()
                    outcome = {"status": "FAILED", "attempts": self.max_retries + 1, "errors": [tb],
                               "traceback": tb, "result": None, "artifacts": {"traceback.txt": tb.encode()}}
                on_done(job, outcome)
        finally:
            if started_here:
                ray.shutdown()


def make_executor(cfg: dict):
    kind = cfg.get("kind")
    if kind == "local":
        return LocalExecutor()
    if kind == "ray":
        return RayExecutor(cfg.get("address"), cfg.get("num_cpus"), cfg.get("gpus_per_job", 0),
                           cfg.get("max_retries", 2))
    raise ValueError(f"executor.kind: must be 'local' or 'ray', got {kind!r}")
