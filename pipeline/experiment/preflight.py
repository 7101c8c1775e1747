"""The checks a sweep makes before any job starts, each one line naming the key or file: every scene
readable and of its dataset's format (the embedded scene generated first), every protocol fitting its
scene with every image it uses decodable, every initial model readable, the output folder writable,
devices and threads this machine has; and the notes a launch prints (skipped jobs from other code, an
up axis the estimates disagree on). ``validate_sweep`` runs them; the driver (``sweep``) calls it."""

from __future__ import annotations

import json
import os
from pathlib import Path

from omegaconf import OmegaConf

from pipeline.data.load import load_scene
from pipeline.active.plan import EpisodePlan
from pipeline.data.scene import Scene
from pipeline.data.generated_cache import cache_from_environment, place_generated
from pipeline.data.synthetic import GeneratedScene, at_fraction
from pipeline.experiment.episode_settings import ConfigError
from pipeline.experiment.console import console
from pipeline.experiment.executors import scene_key
from pipeline.experiment.provenance import code_version, stale_versions
from pipeline.experiment.records import RecordsFile
from pipeline.experiment.spec import Job
from pipeline.interchange.layout import cannot_write
from pipeline.splat import ply

LOG = console()


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
            options, cache = job.generate, cache_from_environment()
            LOG.info(f"generating the default scene into {path} ..." if cache is None else
                     f"the default scene into {path}, from the scene cache {cache} ...")
            # the section's keys are GeneratedScene's fields (checked by the schema); unset ones keep its defaults
            place_generated(path, GeneratedScene(**options), cache, progress=every_quarter)
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


def plan_key(job: Job) -> str:
    """What an episode's plan can fail on: the scene and the episode settings, not the strategy or the
    seed (the episode's, and the fit's copy of it)."""
    settings = {k: v for k, v in job.episode.to_dict().items() if k not in ("strategy", "strategy_options", "seed")}
    settings["fit"] = {k: v for k, v in settings["fit"].items() if k != "seed"}
    return json.dumps([scene_key(job), settings], sort_keys=True, default=str)


def protocol_errors(jobs: list[Job], scenes: dict[str, Scene], decode: bool = True) -> list[str]:
    """One error per (scene, protocol) that does not fit the scene (budget, initial views, an
    empty sector, no extent ...), found by making each distinct episode plan (``EpisodePlan``, what
    the job makes first) before any job starts; with ``decode``, one per image those views use that
    cannot be decoded (a zero-byte file would otherwise fail the job that happens to pick it, mid-sweep)."""
    errors, built, too_many = [], {}, set()
    used: dict[tuple[str, str], set[int]] = {}
    for job in jobs:
        if job.kind != "episode" or scene_key(job) not in scenes:
            continue
        key = plan_key(job)
        if key not in built:  # each distinct plan made once
            try:
                views = EpisodePlan.of(scenes[scene_key(job)], job.episode).views
            except ValueError as err:
                where = f" ({job.setting})" if job.setting else ""
                line = f"protocol on dataset.{job.dataset} scene {job.scene!r}{where}: {err}"
                if line not in errors:  # plans that differ beyond the protocol fail alike: one line
                    errors.append(line)
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
