"""The driver of a sweep: expand, skip what is done, prepare scenes, fan out, track, record.

Relaunching a sweep skips every job whose config hash has a FINISHED run (in MLflow or in the
records file) and reruns the rest; the records file is rewritten after every job, and each job
checkpoints its episode after every round, so a killed sweep loses no finished work.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from pipeline.data.load import load_scene
from pipeline.data.protocols import build_protocol
from pipeline.data.scene import Scene
from pipeline.data.synthetic import at_fraction, generate
from pipeline.experiment.build import ConfigError, expand_jobs
from pipeline.experiment.console import console, sweep_log
from pipeline.experiment.data_changes import SUPERSEDED, data_changes
from pipeline.experiment.executors import make_executor, scene_key
from pipeline.experiment.interrupt import SweepInterrupted, critical, ignore_stop_signals
from pipeline.experiment.layout import SweepFolder
from pipeline.experiment.lock import SweepLock, SweepLocked
from pipeline.experiment.outcome import TRACEBACK_ARTIFACT, JobOutcome, RoundMessage, StepProgress
from pipeline.experiment.provenance import code_version, stale_versions
from pipeline.experiment.records import RecordsFile, job_rows
from pipeline.experiment.replay import finished_not_in, replay, replay_until_taken
from pipeline.experiment.reuse import reuse_finished
from pipeline.experiment.tracking import make_tracker
from pipeline.experiment.warmup import compile_kernels
from pipeline.interchange.layout import cannot_write
from pipeline.splat import ply
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
        path = Path(job.execution.job_dir) / "artifacts" / TRACEBACK_ARTIFACT
        return f"after {outcome.attempts} attempt(s): {last[:300]} (traceback: {path})"
    if outcome.final is not None:
        return (f"test PSNR {outcome.final.psnr:.2f} dB (all {outcome.final.test_views} test views) in "
                f"{outcome.seconds or 0:.0f} s")
    return f"AUSE {json.dumps({k: round(v, 3) for k, v in outcome.uncertainty.ause.items()})}"


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


def every_quarter(split: str, done: int, total: int) -> None:
    """A progress line at each quarter of a split of the generated scene."""
    if at_fraction(done, total, 4):
        LOG.info(f"  {split}: {done}/{total} views")


def reuse_sources(cfg) -> list[Path]:
    """``reuse_from``: the output folders whose finished jobs this sweep takes (``reuse``); [] when
    unset."""
    value = cfg.get("reuse_from")
    if OmegaConf.is_config(value):
        value = OmegaConf.to_container(value, resolve=True)
    value = [] if value is None else [value] if isinstance(value, str) else value
    if not isinstance(value, list) or not all(isinstance(v, str) and v for v in value):
        raise ConfigError(f"reuse_from: expected a list of output folders, e.g. 'reuse_from=[outputs/other]', "
                          f"got {value!r}")
    return [Path(v) for v in value]


def prepare_scenes(jobs: list[Job]) -> tuple[dict[str, Scene], list[str]]:
    """Generate the embedded scene if needed, then read each (scene, resolution) once.
    Returns the scenes and one error per scene that cannot be read (naming the dataset key)."""
    scenes, seen, errors = {}, set(), []
    for job in jobs:
        key = scene_key(job)
        if key in seen:
            continue
        seen.add(key)
        path = Path(job.scene_path).resolve()
        if job.generate and not (path / "transforms_test.json").exists():
            options = job.generate
            LOG.info(f"generating the default scene into {path} ...")
            generate(path, seed=options.get("seed", 0), size=options.get("size", 100),
                     n_train=options.get("n_train", 100), n_test=options.get("n_test", 200),
                     progress=every_quarter)
        try:
            scene = load_scene(path, width=job.episode.fit.image_width, masks=job.masks)
        except Exception as err:
            errors.append(f"dataset.{job.dataset} scene {job.scene!r}: {err}")
            continue
        if scene.format != job.format:
            errors.append(f"dataset.{job.dataset} scene {job.scene!r}: {path} is a {scene.format} "
                          f"scene but dataset.{job.dataset}.format is {job.format!r}")
            continue
        scenes[key] = scene
    return scenes, errors


def protocol_errors(jobs: list[Job], scenes: dict[str, Scene], decode: bool = True) -> list[str]:
    """One error per (scene, protocol) that does not fit the scene (budget, initial views, an
    empty sector ...), found by building the protocol's views before any job starts; with
    ``decode``, one per image those views use that cannot be decoded (a zero-byte file would
    otherwise fail the job that happens to pick it, mid-sweep)."""
    errors, built, too_many = [], {}, set()
    used: dict[tuple[str, str], set[int]] = {}
    for job in jobs:
        if job.kind != "episode" or scene_key(job) not in scenes:
            continue
        key = (scene_key(job), json.dumps(job.protocol, sort_keys=True))
        if key not in built:  # each (scene, protocol) built once
            try:
                views = build_protocol(scenes[scene_key(job)], job.episode.protocol)
            except ValueError as err:
                where = f" ({job.setting})" if job.setting else ""
                errors.append(f"protocol on dataset.{job.dataset} scene {job.scene!r}{where}: {err}")
                views = None
            else:
                used.setdefault((scene_key(job), views.pool_split), set()).update(
                    views.initial_ids + views.pool_ids + views.probe_ids)
                used.setdefault((scene_key(job), views.test_split), set()).update(views.test_ids)
            built[key] = views
        views = built[key]
        if views is not None and job.episode.views_per_round > views.budget - len(views.initial_ids):
            too_many.add((job.dataset, job.scene, job.episode.views_per_round, views.budget, len(views.initial_ids)))
    errors += [f"splat.views_per_round: {per_round} is more than the {budget - initial} picks the protocol leaves "
               f"on dataset.{dataset} scene {scene!r} (budget {budget}, {initial} initial views)"
               for dataset, scene, per_round, budget, initial in sorted(too_many)]
    if decode:
        for (key, split), ids in used.items():
            errors += scenes[key].split(split).images.check_decodable(sorted(ids))
    return errors


def init_errors(jobs: list[Job]) -> list[str]:
    """splat.init=ply:PATH must name a readable 3DGS PLY."""
    errors = []
    for path in sorted({j.splat["init"][len("ply:"):] for j in jobs if j.splat.get("init")}):
        try:
            ply.load(path)
        except (OSError, ValueError) as err:
            errors.append(f"splat.init: {err}")
    return errors


def validate_sweep(jobs: list[Job], decode_images: bool = True) -> dict[str, Scene]:
    """Read every scene, build every protocol and (``decode_images``) decode every image the
    protocols use, before Ray or MLflow start; all problems are reported at once as one
    ConfigError (one line each)."""
    scenes, errors = prepare_scenes(jobs)
    errors += protocol_errors(jobs, scenes, decode_images) + init_errors(jobs)
    if errors:
        raise ConfigError(f"{len(errors)} problem(s), nothing was started:\n  " + "\n  ".join(errors))
    for line in orientation_warnings(jobs, scenes):
        LOG.warning(line)
    return scenes


def orientation_warnings(jobs: list[Job], scenes: dict[str, Scene]) -> list[str]:
    """One line per scene whose up axis (the one its jobs use) disagrees with the other estimates
    (``pipeline.data.orientation``): the goal protocol's sector would be taken about a tilted axis."""
    from pipeline.data.orientation import orientation
    out, seen = [], set()
    for job in jobs:
        key = scene_key(job)
        choice = job.episode.protocol.up
        if key not in scenes or (key, str(choice)) in seen:
            continue
        seen.add((key, str(choice)))
        scene = scenes[key]
        if choice is None and scene.info.get("up") is None and scene.traits.up == "z":
            continue  # the layout says +z (Blender)
        warning = orientation(scene.all_cameras(), scene.points, choice or scene.info.get("up")).warning()
        if warning:
            out.append(f"warning: dataset.{job.dataset} scene {job.scene!r}: {warning}")
    return out


def warn_stale(name: str, records: RecordsFile, skipped: set[str], output_dir: Path) -> None:
    """Say when skipped jobs were computed by other code than the code running now."""
    current = code_version()
    finished = {h: v for h, v in records.finished_versions().items() if h in skipped}
    for version, count in stale_versions(finished, current).items():
        LOG.info(f"[{name}] note: {count} skipped job(s) were computed by code {version}, this is "
                 f"{current}; their results are kept. Use a new output_dir to recompute them "
                 f"(or delete {output_dir / 'records.parquet'} and the MLflow runs).")


def no_device_here(executor, jobs: list[Job]) -> None:
    """``job.device=cuda`` for jobs that run on this machine, which has no CUDA device: one
    ConfigError now (each job would otherwise fail at its first tensor)."""
    import torch
    if executor.runs_here and any(j.execution.device == "cuda" for j in jobs) and not torch.cuda.is_available():
        raise ConfigError("job.device: 'cuda', but the jobs run on this machine and it has no CUDA device "
                          "(torch.cuda.is_available() is False): use job.device=cpu, or run on a cluster "
                          "whose nodes have GPUs (executor.address / executor=slurm)")


def more_threads_than_cores(executor, jobs: list[Job], cores: int | None = None) -> str | None:
    """The warning for jobs that run on this machine with more threads than it has cores (each
    job would oversubscribe the CPU, slower than asking for what is there); None when they fit."""
    cores = cores or os.cpu_count() or 1
    wanted = max((j.execution.threads for j in jobs), default=0)
    if not executor.runs_here or wanted <= cores:
        return None
    return (f"warning: job.threads={wanted}, but the jobs run on this machine, which has {cores} cores: each "
            f"job will share them (job.threads={cores} uses them all)")


def compiles_here(executor, jobs: list[Job]) -> bool:
    """The jobs run on this machine's CPU (``executor.runs_here``): compile the kernels here first
    when their cache is missing. Jobs on a cluster compile on their nodes."""
    return executor.runs_here and any(j.execution.device == "cpu" for j in jobs)


def writable_folder(folder: Path, key: str) -> None:
    """``folder`` exists or can be made, and takes a file: else one ConfigError naming ``key``."""
    problem = cannot_write(folder, folder=True)
    if problem is not None:
        raise ConfigError(f"{key}={folder}: {problem}")


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
        self.todo: list[dict] = []
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
            self.progress = Progress(self.name, len(self.todo), getattr(self.executor, "slots", 1))
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
        self.progress.slots = getattr(self.executor, "slots", 1)
        self.progress.update(job, outcome)

    def on_round(self, job: Job, message: RoundMessage | StepProgress) -> None:
        if isinstance(message, StepProgress):  # inside a round: a console line, nothing tracked
            LOG.info(f"[{self.name}] {job.label}: {message.text()}")
            return
        with critical():
            self.track_round(job, message)

    def track_round(self, job: Job, message: RoundMessage) -> None:
        self.progress.slots = max(1, getattr(self.executor, "slots", 1))  # known once the executor started
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
