"""The driver of a sweep: expand, skip what is done, prepare scenes, fan out, track, record.

Relaunching a sweep skips every job whose config hash has a FINISHED run (in MLflow or in the
records file) and reruns the rest; the records file is rewritten after every job, and each job
checkpoints its episode after every round, so a killed sweep loses no finished work.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from pipeline.data.scene import Scene
from pipeline.experiment.episode_settings import ConfigError
from pipeline.experiment.build import expand_jobs
from pipeline.experiment.console import console, sweep_log
from pipeline.experiment.data_changes import SUPERSEDED, data_changes
from pipeline.experiment.executors import make_executor
from pipeline.experiment.interrupt import SweepInterrupted, critical, ignore_stop_signals
from pipeline.experiment.layout import SweepFolder
from pipeline.experiment.lock import SweepLock, SweepLocked
from pipeline.experiment.preflight import (compiles_here, more_threads_than_cores, no_device_here,  # noqa: F401
                                           prepare_scenes, reuse_sources, validate_sweep, warn_stale,
                                           writable_folder)
from pipeline.experiment.progress import Progress  # noqa: F401
from pipeline.experiment.outcome import JobOutcome, RoundMessage, StepProgress
from pipeline.experiment.records import RecordsFile, job_rows
from pipeline.experiment.replay import finished_not_in, replay, replay_until_taken
from pipeline.experiment.reuse import reuse_finished
from pipeline.experiment.tracking import make_tracker
from pipeline.experiment.warmup import compile_kernels
from pipeline.experiment.spec import Job

LOG = console()
DEFAULT_REPLAY_WAIT_S = 120.0  # tracking.replay_wait_s's default (schema.TrackingSection)


@dataclass
class SweepSummary:
    name: str
    output_dir: str
    jobs: int
    skipped: int
    finished: int
    failed: int
    seconds: float
    tracking_uri: str | None
    interrupted: list[str] = field(default_factory=list)  # config hashes a stop signal cut short
    stopped_by: str | None = None
    untracked: list[str] = field(default_factory=list)  # finished jobs MLflow did not receive
    experiment_id: str | None = None  # the MLflow experiment of the sweep (None: no tracking)


def save_artifacts(output_dir: Path, job: Job, outcome: JobOutcome) -> None:
    """Artifacts also go to <output_dir>/jobs/<hash>/artifacts (what reports read offline)."""
    job_folder = SweepFolder(output_dir).job(job.config_hash)
    folder = job_folder.artifacts
    for name, data in outcome.artifacts.items():
        path = folder / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)
    if outcome.result is not None:
        folder.mkdir(parents=True, exist_ok=True)
        job_folder.result_file.write_text(json.dumps(outcome.result, default=str))


def acquire_lock(output_dir: Path) -> SweepLock:
    """``output_dir``'s lock (one driver per folder: a sweep or a tracking replay), or a ConfigError
    saying who holds it."""
    try:
        return SweepLock(output_dir).acquire()
    except SweepLocked as err:
        raise ConfigError(str(err)) from None


def execution_order(jobs: list[Job]) -> list[Job]:
    """Seed by seed (then the config's order): a sweep stopped early has every method of the
    first seeds, which is what paired comparisons need, rather than some methods on all seeds."""
    return sorted(jobs, key=lambda j: (j.seed, j.index))


def run_sweep(cfg: DictConfig) -> SweepSummary:
    """Expand, validate and run a sweep (one sweep at a time per output folder)."""
    start = time.perf_counter()
    jobs = expand_jobs(cfg)
    output_dir = Path(str(cfg.output_dir))
    writable_folder(output_dir, "output_dir")
    lock = acquire_lock(output_dir)
    try:
        with sweep_log(output_dir):
            return _locked_sweep(cfg, jobs, output_dir, start, lock)
    finally:
        lock.release()


def _locked_sweep(cfg: DictConfig, jobs: list[Job], output_dir: Path, start: float, lock) -> SweepSummary:
    if lock.stale is not None:
        LOG.info(f"[{cfg.name}] note: took over a stale lock of a sweep that no longer runs "
                 f"(pid {lock.stale.get('pid')}, since {lock.stale.get('since')})")
    return SweepRun(cfg, jobs, output_dir, start).run(stale_driver=lock.stale is not None)


class SweepRun:
    """One launch of a sweep, from the validated jobs to the summary: what it has to do
    (``todo``), where results go (records, tracker, artifacts) and what it counted so far.

    ``run`` prepares (validation, tracking, the skip list), fans the jobs out on the executor,
    hears each finished job (``record``) and round (``track_round``) under ``critical()`` so a stop
    signal waits for the bookkeeping, and ends with a summary (``interrupted`` on a stop signal)."""

    def __init__(self, cfg: DictConfig, jobs: list[Job], output_dir: Path, start: float):
        self.name, self.jobs, self.output_dir, self.start = str(cfg.name), jobs, output_dir, start
        self.cfg = cfg
        self.resolved = OmegaConf.to_container(cfg, resolve=True)
        self.folder = SweepFolder(output_dir)
        self.records = RecordsFile(output_dir)
        self.failed, self.untracked = 0, []
        self.tracker = self.executor = self.progress = None
        self.todo: list[Job] = []
        self.by_hash = {j.config_hash: j for j in jobs}  # what a replay looks its jobs up in
        self.tracked: set[str] = set()  # the config hashes the store has as FINISHED (prepare)

    def run(self, stale_driver: bool = False) -> SweepSummary:
        scenes = self.prepare(stale_driver)
        # this sweep's jobs finished here that the store does not have (a server that was away)
        missing = ([h for h in finished_not_in(self.records, self.tracked) if h in self.by_hash]
                   if self.tracker.uri else [])
        if missing:  # replayed first
            with critical():
                self.tracker.start(self.resolved, len(self.todo))
                done = replay_until_taken(self.tracker, self.by_hash, self.output_dir, self.records, missing, 0.0,
                                          lambda line: LOG.info(f"[{self.name}] {line}"))
            LOG.info(f"[{self.name}] tracking: {len(missing)} finished job(s) were not in {self.tracker.uri}: "
                     f"{done.line()}")
            self.untracked += done.failed
        if self.todo and compiles_here(self.executor, self.todo):
            compile_kernels(lambda line: LOG.info(f"[{self.name}] {line}"))
        if self.todo:
            self.progress = Progress(self.name, len(self.todo), self.executor.slots)
            try:
                if not missing:  # (the replay above opened the sweep's run already)
                    with critical():
                        self.tracker.start(self.resolved, len(self.todo))
                self.executor.map(self.todo, scenes, self.on_done, self.on_round)
            except SweepInterrupted as stop:
                self.interrupted(stop)
                raise
            except Exception:  # the executor refused to run (a node's probe, auth): no run stays RUNNING
                with critical():
                    try:
                        self.tracker.end({"failed": len(self.todo) - self.progress.done + self.failed})
                    except Exception as err:  # the error that stopped the sweep is the one to say
                        LOG.warning(f"[{self.name}] warning: could not close the sweep's MLflow run: "
                                    f"{str(err).splitlines()[0][:300]}")
                raise
        return self.finish()

    def prepare(self, stale_driver: bool) -> dict[str, Scene]:
        """Write the resolved config, validate what is left to run, open the tracker, decide the
        skip list and the execution order; the scenes the jobs read."""
        self.folder.config_file.write_text(json.dumps(self.resolved, indent=1, default=str))
        self.supersede_changed_data()
        for taken in reuse_finished(self.jobs, reuse_sources(self.cfg), self.output_dir, self.records):
            LOG.info(f"[{self.name}] reused {len(taken.hashes)} finished job(s) from {taken.source}: their job folders "
                     "and records rows, which keep their code version (the records' reused_from names the folder)")
        recorded = self.records.finished_hashes()
        scenes = validate_sweep([j for j in self.jobs if j.config_hash not in recorded],
                                bool(self.cfg.get("validate_images", True)))
        self.tracker = make_tracker(self.resolved["tracking"], self.output_dir, self.name)
        # this driver holds output_dir's lock: a run of this folder still RUNNING belongs to a driver
        # that died (killed, crashed, or lost its tracking server); it ends KILLED, and a report
        # reads each job's FINISHED run (records.current_runs)
        closed = self.tracker.close_stale_runs()
        if closed:
            why = "the killed driver" if stale_driver else "an earlier driver that did not end them"
            LOG.info(f"[{self.name}] note: {len(closed)} MLflow run(s) left RUNNING by {why} marked KILLED")
        self.tracked = self.tracker.finished_hashes()
        done = recorded | self.tracked
        self.todo = execution_order([j for j in self.jobs if j.config_hash not in done])
        LOG.info(f"[{self.name}] {len(self.jobs)} jobs: {len(self.jobs) - len(self.todo)} already finished "
                 f"(skipped), {len(self.todo)} to run; output in {self.output_dir}")
        warn_stale(self.name, self.records, {j.config_hash for j in self.jobs} & done, self.output_dir)
        self.folder.write_jobs(self.jobs)
        self.executor = make_executor(self.resolved["executor"], self.output_dir)
        no_device_here(self.executor, self.todo)
        oversubscribed = more_threads_than_cores(self.executor, self.todo)
        if oversubscribed:
            LOG.warning(f"[{self.name}] {oversubscribed}")
        return scenes

    def supersede_changed_data(self) -> None:
        """Name each scene whose data changed since its jobs finished here, and move those records
        aside (``data_changes``): the jobs re-run under their new hashes."""
        changes = data_changes(self.jobs, self.records.frame)
        for change in changes:
            LOG.info(f"[{self.name}] {change.line()}; their old records moved to {SUPERSEDED}")
        if changes:
            self.records.supersede(set().union(*(c.hashes for c in changes)))

    def on_done(self, job: Job, outcome: JobOutcome) -> None:
        with critical():  # a stop signal waits until the job is recorded and tracked
            self.record(job, outcome)

    def record(self, job: Job, outcome: JobOutcome) -> None:
        self.failed += not outcome.finished
        try:
            run_id = self.tracker.log_job(job, outcome)
        except Exception as err:  # tracking trouble must not lose the job's records
            LOG.warning(f"[{self.name}] warning: tracking failed for {job.config_hash}: "
                        f"{str(err).splitlines()[0][:300]}")
            run_id = None
            self.untracked.append(job.config_hash)
        save_artifacts(self.output_dir, job, outcome)
        self.records.add(job_rows(job, outcome, run_id))
        self.progress.slots = self.executor.slots
        self.progress.update(job, outcome)

    def on_round(self, job: Job, message: RoundMessage | StepProgress) -> None:
        if isinstance(message, StepProgress):  # inside a round: a console line, nothing tracked
            LOG.info(f"[{self.name}] {job.label}: {message.text()}")
            return
        with critical():
            self.track_round(job, message)

    def track_round(self, job: Job, message: RoundMessage) -> None:
        self.progress.slots = max(1, self.executor.slots)  # known once the executor started
        self.progress.round(job, message)
        try:
            self.tracker.log_round(job, message)
        except Exception as err:  # tracking trouble must not stop the sweep
            LOG.warning(f"[{self.name}] warning: tracking a round failed for {job.config_hash}: {err}")

    def summary(self, finished: int, **extra) -> SweepSummary:
        return SweepSummary(self.name, str(self.output_dir), len(self.jobs), len(self.jobs) - len(self.todo),
                            finished, self.failed, round(time.perf_counter() - self.start, 1), self.tracker.uri,
                            experiment_id=getattr(self.tracker, "experiment_id", None), **extra)

    def interrupted(self, stop: SweepInterrupted) -> None:
        ignore_stop_signals()  # a second Ctrl-C must not cut the bookkeeping short
        interrupted = [j.config_hash for j in getattr(self.executor, "running", [])]
        finished = self.progress.done - self.failed
        summary = self.summary(finished, interrupted=interrupted, stopped_by=str(stop))
        self.tracker.interrupt(asdict(summary))
        self.folder.summary_file.write_text(json.dumps(asdict(summary), indent=1))
        LOG.info(f"[{self.name}] {stop}: finished {finished}, failed {self.failed}, interrupted "
                 f"{len(interrupted)}, not started {len(self.todo) - self.progress.done - len(interrupted)} of "
                 f"{len(self.todo)} jobs; relaunch the same command to resume (interrupted jobs continue from "
                 f"their last round checkpoint)")

    def finish(self) -> SweepSummary:
        if self.untracked:  # the server went away: try again while it comes back, then say what is left
            wait = float(self.resolved["tracking"].get("replay_wait_s", DEFAULT_REPLAY_WAIT_S))
            with critical():
                done = replay_until_taken(self.tracker, self.by_hash, self.output_dir, self.records,
                                          list(dict.fromkeys(self.untracked)), wait,
                                          lambda line: LOG.info(f"[{self.name}] {line}"))
            if done.replayed:
                LOG.info(f"[{self.name}] tracking: {done.line()}")
            self.untracked = done.failed
        summary = self.summary(len(self.todo) - self.failed, untracked=self.untracked)
        try:
            self.tracker.end(asdict(summary))
        except Exception as err:
            LOG.warning(f"[{self.name}] warning: could not close the sweep's MLflow run: "
                        f"{str(err).splitlines()[0][:300]}")
        if self.untracked:
            LOG.info(f"[{self.name}] {len(self.untracked)} finished job(s) could not be tracked "
                     f"({', '.join(self.untracked)}); their results are in records.parquet and jobs/<hash>/: "
                     f"the next launch of the same command replays them once the tracking server answers "
                     f"(tracking_sync=true replays them without running anything)")
        self.folder.summary_file.write_text(json.dumps(asdict(summary), indent=1))
        return summary


def sync_tracking(cfg: DictConfig) -> dict:
    """Replay into MLflow every finished job of the records that the tracking store does not have
    as FINISHED (a tracking server that was down), from records.parquet and jobs/<hash>/. Runs no
    job (``replay``). Returns the replayed and the unknown config hashes."""
    jobs = {j.config_hash: j for j in expand_jobs(cfg)}
    output_dir = Path(str(cfg.output_dir))
    records = RecordsFile(output_dir)
    resolved = OmegaConf.to_container(cfg, resolve=True)
    lock = acquire_lock(output_dir)  # no sweep may run in this folder while it is replayed
    try:
        tracker = make_tracker(resolved["tracking"], output_dir, str(cfg.name))
        closed = tracker.close_stale_runs()  # partial runs of the outage, the parent left open
        have = tracker.finished_hashes()
        done = replay(tracker, jobs, output_dir, records, finished_not_in(records, have))
        LOG.info(f"[{cfg.name}] tracking sync: {done.line()} into {tracker.uri}, "
                 f"{len(have & set(jobs))} already there, {len(closed)} left RUNNING marked KILLED")
        return {"synced": done.replayed, "unknown": done.unknown}
    finally:
        lock.release()
