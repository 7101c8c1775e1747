"""Executors: run jobs and hand each outcome to the driver as soon as it is ready.

``local`` runs jobs one after another in this process. ``ray`` runs one Ray task per job on a
local Ray (started with this machine's cores) or a running cluster (``address``); each task
reserves ``execution.threads`` CPUs (and ``gpus_per_job`` GPUs), scenes go into the object store
once per (scene, resolution), and results are collected with ``ray.wait`` as they finish. Both
call the same ``run_with_retries``, so they give the same numbers at the same seed.

Progress from inside a job: ``on_round(job, message)`` hears every finished round while the job
runs. Locally it is called directly; under Ray the tasks put their messages on a Ray queue (an
actor that takes no CPU) that the driver drains while it waits for results.
"""

from __future__ import annotations

import os
import traceback
from pathlib import Path
from typing import Callable

from pipeline.data.scene import Scene
from pipeline.experiment.interrupt import (SweepInterrupted, critical, current_handlers,
                                           install_stop_handlers, restore_handlers)
from pipeline.experiment.job import run_with_retries
from pipeline.experiment.outcome import JobOutcome, RoundMessage
from pipeline.experiment.spec import Job

OnDone = Callable[[dict, JobOutcome], None]
OnRound = Callable[[dict, RoundMessage], None]
POLL_SECONDS = 0.5  # how often the Ray driver looks for round messages while jobs run


class LocalExecutor:
    slots = 1

    def __init__(self):
        self.running: list[Job] = []  # the jobs a stop signal interrupted (see SweepInterrupted)

    def map(self, jobs: list[Job], scenes: dict[str, Scene], on_done: OnDone,
            on_round: OnRound | None = None) -> None:
        for job in jobs:
            report = None if on_round is None else (lambda message, job=job: on_round(job, message))
            self.running = [job]
            outcome = run_with_retries(job, scenes.get(scene_key(job)), report)
            self.running = []
            on_done(job, outcome)


def scene_key(job: Job) -> str:
    return f"{job.scene_path}@{job.splat.get('image_width')}/{job.splat['preset']}" + ("+masks" if job.masks else "")


def _remote_run(plain_job: dict, scene: Scene | None, queue=None) -> dict:
    """A Ray task: the job arrives and the outcome leaves as plain data (``Job.to_dict``,
    ``JobOutcome.to_dict``)."""
    job = Job.from_dict(plain_job)
    report = None
    if queue is not None:
        def report(message: RoundMessage) -> None:
            queue.put_nowait((job.config_hash, message.to_dict()))
    return run_with_retries(job, scene, report).to_dict()


class RoundChannel:
    """Round messages from Ray tasks to the driver, through a Ray queue actor that takes no CPU."""

    def __init__(self, jobs: list[Job], on_round: OnRound):
        from ray.util.queue import Queue

        self.queue = Queue(actor_options={"num_cpus": 0})
        self.jobs = {job.config_hash: job for job in jobs}
        self.on_round = on_round

    def drain(self) -> None:
        while True:
            with critical():  # the queue's calls are Ray calls: a stop signal waits for them
                if self.queue.empty():
                    return
                config_hash, message = self.queue.get_nowait()
            self.on_round(self.jobs[config_hash], RoundMessage.from_dict(message))

    def close(self) -> None:
        self.queue.shutdown()


class RayExecutor:
    def __init__(self, address: str | None = None, num_cpus: int | None = None, gpus_per_job: float = 0,
                 max_retries: int = 2):
        self.address, self.num_cpus = address, num_cpus
        self.gpus_per_job, self.max_retries = gpus_per_job, max_retries
        self.slots = 1
        self.running: list[Job] = []  # the jobs a stop signal interrupted (see SweepInterrupted)

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

    def map(self, jobs: list[Job], scenes: dict[str, Scene], on_done: OnDone,
            on_round: OnRound | None = None) -> None:
        previous = current_handlers()  # restored when the sweep ends
        ray, started_here, channel, pending = None, False, None, {}
        try:
            # Every Ray call runs with stop signals deferred (``critical``): a handler that raised
            # inside Ray's Cython code would surface as a SystemError instead of a clean stop, and
            # one inside ray.init left a half-started Ray that crashed the exit; the request is
            # acted on as soon as the call returns (at most one poll later).
            with critical():
                ray, started_here = self._start()
                install_stop_handlers()  # after ray.init, which installs its own SIGTERM handler
                channel = RoundChannel(jobs, on_round) if on_round is not None else None
                refs = {key: ray.put(scene) for key, scene in scenes.items()}  # once per scene
            cpus = ray.cluster_resources().get("CPU", 1)
            self.slots = max(1, int(cpus // max(1, min(j.execution.threads for j in jobs)))) if jobs else 1
            task = ray.remote(_remote_run)
            with critical():
                for job in jobs:
                    options = {"num_cpus": job.execution.threads, "num_gpus": self.gpus_per_job,
                               "max_retries": self.max_retries, "name": f"{job.method}:{job.scene}"}
                    queue = channel.queue if channel is not None else None
                    pending[task.options(**options).remote(job.to_dict(), refs.get(scene_key(job)), queue)] = job
            while pending:
                with critical():
                    done, _ = ray.wait(list(pending), num_returns=1, timeout=POLL_SECONDS)
                if channel is not None:  # a job's rounds are all heard before its end
                    channel.drain()
                if not done:
                    continue
                job = pending.pop(done[0])
                try:
                    with critical():
                        outcome = JobOutcome.from_dict(ray.get(done[0]))
                except Exception:  # the worker died more often than max_retries allows
                    outcome = JobOutcome.failed(self.max_retries + 1, [traceback.format_exc()])
                on_done(job, outcome)
        except SweepInterrupted:
            self.running = self._cancel(ray, pending) if ray is not None else []
            raise
        finally:
            if channel is not None:
                channel.close()
            if started_here:
                ray.shutdown()
            restore_handlers(previous)  # the caller's handlers (the CLI's own, or a test runner's)

    @staticmethod
    def _cancel(ray, pending: dict) -> list[Job]:
        """Cancel every pending task (force: the worker processes stop); returns the jobs that
        had started (those that never started are simply not run)."""
        started = []
        for ref, job in pending.items():
            try:
                ray.cancel(ref, force=True)
            except Exception:  # already finished or gone: nothing to stop
                pass
            if Path(job.execution.job_dir).exists():  # run_job made its folder: it started
                started.append(job)
        return started


def make_executor(cfg: dict):
    kind = cfg.get("kind")
    if kind == "local":
        return LocalExecutor()
    if kind == "ray":
        return RayExecutor(cfg.get("address"), cfg.get("num_cpus"), cfg.get("gpus_per_job", 0),
                           cfg.get("max_retries", 2))
    raise ValueError(f"executor.kind: must be 'local' or 'ray', got {kind!r}")
