"""From the composed sweep config, as plain data, to its jobs: datasets x scenes x methods x seeds x
sweep axes, each a validated ``Job`` with its config hash. No Hydra here: ``build`` (the Hydra room)
turns the composed config into plain data once and hands it to ``resolve_jobs``.

Every job is validated while it is made (its episode config, its strategy's options), so a bad value
fails at start-up naming its key. A method's strategy is resolved once (its plugin identity) and
built once per distinct set of options (the strategy is its options' typed dataclass: bounded
fields, checked when built); jobs that differ only in seed, scene or a non-option axis share it.
"""

from __future__ import annotations

import copy
import itertools
import json
from dataclasses import dataclass
from pathlib import Path

from pipeline.acquisition import POSE_SCORING, REGISTRY as BUILT_IN, make_strategy, scores_any_pose
from pipeline.acquisition.base import Strategy
from pipeline.acquisition.discovery import StrategyError, check_plugins, resolve_strategy
from pipeline.bounds import BoundsError
from pipeline.data.fingerprint import FileDigests, generated_fingerprint, scene_fingerprint
from pipeline.data.images import DataError
from pipeline.experiment.episode_settings import ConfigError, check_keys, uncertainty_config, world_section
from pipeline.experiment.layout import SweepFolder
from pipeline.experiment.provenance import code_version
from pipeline.experiment.schema import config_problems
from pipeline.experiment.spec import RESULTS_REVISION, Job, config_hash
from pipeline.experiment.splat_section import job_form
from pipeline.fit.config import dotted_leaves

# protocol/splat: overrides for this method; world: this method's capture simulator (gopre_search)
METHOD_KEYS = {"strategy", "options", "protocol", "splat", "world"}
DATASET_KEYS = {"format", "root", "scenes"}
MISSING_DATA = "unreadable"


@dataclass(frozen=True)
class SweepSections:
    """The composed config's sections a sweep's jobs are made of, as plain data."""

    name: str
    output_dir: Path
    datasets: dict[str, dict]       # the selected datasets (a preset's leftovers for others dropped)
    methods: dict[str, dict]
    protocol: dict
    splat: dict                     # reduced to what differs from its preset (``splat_section.job_form``)
    job: dict
    world: dict | None              # the capture simulator (None: the dataset's pool)
    tracked: bool                   # MLflow tracking on (round images are made only then)
    uncertainty: dict | None
    seeds: list[int]
    axes: list[dict]                # one dict per combination of the sweep axes' values

    @classmethod
    def of(cls, config: dict) -> "SweepSections":
        """Checked: every declared bound (one error listing every bad value), the seeds, the axes,
        the selection and the datasets' keys, before any job is built."""
        datasets = {d: v for d, v in (config.get("dataset") or {}).items() if set(v or {}) & DATASET_KEYS}
        # a preset's settings for a dataset the list does not select (e.g. experiment=debug dataset=shared:
        # debug sizes the generated scene) hold none of these keys: not a dataset here
        if not datasets:
            raise ConfigError("dataset: no dataset selected")
        if not config.get("method"):
            raise ConfigError("method: no method selected")
        check_declared(config)
        world = world_section(config.get("world") or {"kind": "dataset"})
        try:
            splat = job_form(config["splat"])
        except ValueError as err:
            raise ConfigError(f"splat.{err}") from None
        for dname, dset in datasets.items():
            missing = sorted(DATASET_KEYS - set(dset))
            if missing:
                raise ConfigError(f"dataset.{dname}: missing keys {missing} (selected: {sorted(datasets)})")
        return cls(name=str(config["name"]), output_dir=Path(str(config["output_dir"])).absolute(),
                   datasets=datasets, methods=config["method"], protocol=config["protocol"], splat=splat,
                   job=config["job"], world=world,
                   tracked=(config.get("tracking") or {}).get("kind") == "mlflow",
                   uncertainty=config.get("uncertainty"), seeds=seeds_of(config.get("seeds")),
                   axes=sweep_axes(config.get("sweep") or {}))


def check_declared(config: dict) -> None:
    """Every value against its declared bound (``experiment.schema``): one ConfigError listing every
    bad value, key by key."""
    problems = config_problems(config)
    if problems:
        raise ConfigError(problems[0] if len(problems) == 1 else
                          f"{len(problems)} bad values, nothing was started:\n  " + "\n  ".join(problems))


def seeds_of(value: object) -> list[int]:
    """``seeds``: a list of integers (or one integer); anything else is a config error."""
    seeds = [value] if isinstance(value, int) and not isinstance(value, bool) else value
    if not isinstance(seeds, list) or not seeds or any(
            isinstance(s, bool) or not isinstance(s, int) for s in seeds):
        raise ConfigError(f"seeds: expected a non-empty list of integers, e.g. seeds=[0,1,2], got {seeds!r}")
    if any(s < 0 for s in seeds):
        raise ConfigError(f"seeds: a seed must be >= 0, got {seeds!r}")
    if len(set(seeds)) != len(seeds):  # each job would run twice and its records be duplicated
        raise ConfigError(f"seeds: {seeds!r} lists a seed twice")
    return seeds


def sweep_axes(sweep: dict) -> list[dict]:
    """Sweep axes: every list leaf of ``sweep`` (nested like the job, e.g. sweep.protocol.probes)."""
    leaves = dotted_leaves(sweep)
    for key, values in leaves.items():
        if not isinstance(values, list) or not values:
            raise ConfigError(f"sweep.{key}: expected a non-empty list of values, got {values!r}")
    keys = sorted(leaves)
    return [dict(zip(keys, combo)) for combo in itertools.product(*(leaves[k] for k in keys))]  # type: ignore[call-overload]


def _set_dotted(job: dict, dotted: str, value) -> None:
    node, parts = job, dotted.split(".")
    if parts[:2] == ["splat", "fit"]:  # a job carries only the changed fit values: make room
        room = job["splat"]
        for part in parts[1:-1]:
            room = room.setdefault(part, {})
    for part in parts[:-1]:
        if not isinstance(node.get(part), dict):
            raise ConfigError(f"sweep: {dotted!r} is not a job key (no {part!r})")
        node = node[part]
    # a strategy may take an option not set yet; a fit value is checked by episode_config
    if parts[-1] not in node and parts[:-1] != ["options"] and parts[:2] != ["splat", "fit"]:
        raise ConfigError(f"sweep: {dotted!r} is not a job key; job keys: protocol.*, splat.*, options.*, "
                          "renders, uncertainty.*")
    node[parts[-1]] = value


def data_fingerprint(scene_path: str, generate: dict | None, masks: bool, digests: FileDigests) -> str:
    """The scene's data identity for a job's hash (``pipeline.data.fingerprint``): the digest of its
    files; for the generated scene, its options and its generator's identity (the files are made from
    them, so an edited generator is other data); ``MISSING_DATA`` when the folder cannot be read (the
    pre-flight check then names the problem)."""
    if generate is not None:
        return generated_fingerprint(generate)
    try:
        return scene_fingerprint(scene_path, masks, digests).short
    except (DataError, OSError):
        return MISSING_DATA


def strategy_plugins(methods: dict) -> dict[str, dict | None]:
    """Each method's plugin identity (None for a built-in strategy), every strategy resolved once
    before any job is built: an unknown name, a plugin that cannot load, lacks ``select`` or
    reuses a built-in name is a config error naming the method and the entry point or path."""
    for mname, method in methods.items():
        if not isinstance(method, dict) or "strategy" not in method:
            raise ConfigError(f"method.{mname}: missing key 'strategy' (a built-in name, an installed "
                              "plugin's name or package.module:Class)")
        if mname in BUILT_IN and method["strategy"] != mname:  # the row would say 'random' and be another method
            raise ConfigError(f"method.{mname}: the key {mname!r} is the built-in strategy's name, but its strategy "
                              f"is {method['strategy']!r}; give the method another key (e.g. {mname}_variant)")
    try:
        check_plugins({str(m["strategy"]) for m in methods.values()}, warn=_warn)
    except StrategyError as err:
        raise ConfigError(str(err)) from None
    out = {}
    for mname, method in methods.items():
        try:
            source = resolve_strategy(method["strategy"])
        except StrategyError as err:
            raise ConfigError(f"method.{mname}: {err}") from None
        out[mname] = source.plugin.to_dict() if source.plugin is not None else None
    return out


def _warn(line: str) -> None:
    from pipeline.experiment.console import console
    console().warning(line)


class MethodStrategies:
    """Each method's strategy built from its options once per distinct set of options (seeds, scenes
    and axes that do not touch the options share it): a bad option is a config error naming
    ``method.<name>.options.<key>``."""

    def __init__(self) -> None:
        self._built: dict[tuple[str, str, str], Strategy] = {}

    def __call__(self, job: Job) -> Strategy:
        key = (job.method, job.strategy, json.dumps(job.options, sort_keys=True, default=str))
        if key not in self._built:
            try:
                self._built[key] = make_strategy(job.strategy, **job.options)
            except BoundsError as err:
                raise ConfigError(err.under(f"method.{job.method}.options.")) from None
            except ValueError as err:
                raise ConfigError(f"method.{job.method}: {err}") from None
        return self._built[key]


def validate_job(job: Job, strategies: MethodStrategies) -> None:
    """A job that cannot run is a config error naming the key: its episode config (resolved here,
    once, and kept), its strategy's options, a pose search without a strategy that scores any pose."""
    job.episode  # resolved once here, at start-up; a bad value is a config error naming the key
    strategy = strategies(job)
    if job.world is not None and not scores_any_pose(strategy):
        raise ConfigError(f"method.{job.method}: world={job.world['kind']} searches poses off the pool, which "
                          f"needs a strategy that scores any camera ({', '.join(POSE_SCORING)}); {job.strategy!r} "
                          "picks from the pool only")
    if job.kind == "uncertainty":
        uncertainty_config(job)


def resolve_jobs(config: dict) -> list[Job]:
    """Every job of the sweep (``config``: the composed config as plain data), validated, in a
    deterministic order (the config's)."""
    sweep = SweepSections.of(config)
    plugins = strategy_plugins(sweep.methods)
    for mname, method in sweep.methods.items():
        check_keys(f"method.{mname}", method, METHOD_KEYS)
    strategies = MethodStrategies()
    jobs: list[Job] = []
    digests, fingerprints = FileDigests(), {}
    version = code_version()
    for (dname, dset), (mname, method), seed, axes in itertools.product(
            sweep.datasets.items(), sweep.methods.items(), sweep.seeds, sweep.axes):
        for scene in dset["scenes"]:
            job = _plain_job(sweep, dname, dset, scene, mname, method, int(seed), axes)
            if plugins[mname] is not None:  # the plugin's code is part of what the job computes
                job["plugin"] = plugins[mname]
            data_key = (job["scene_path"], json.dumps(job["generate"], sort_keys=True), bool(job.get("masks")))
            if data_key not in fingerprints:  # each scene's files hashed once per launch (and cached on disk)
                fingerprints[data_key] = data_fingerprint(job["scene_path"], job["generate"], data_key[2], digests)
            job["data_fingerprint"] = fingerprints[data_key]
            job["config_hash"] = config_hash(job)
            job["execution"] = _execution(sweep, job["config_hash"])
            job["index"] = len(jobs)  # the order the config lists things in (tables keep it)
            job["code_version"] = version
            typed = Job.from_dict(job)
            validate_job(typed, strategies)
            jobs.append(typed)
    digests.save()
    return jobs


def _plain_job(sweep: SweepSections, dname: str, dset: dict, scene: str, mname: str, method: dict,
               seed: int, axes: dict) -> dict:
    """One job's plain form before its identity (the keys ``jobs.json`` has always held)."""
    job = {"sweep": sweep.name, "results_revision": RESULTS_REVISION,
           "kind": sweep.job["kind"], "dataset": dname,
           "format": dset["format"], "scene": scene,
           "scene_path": str((Path(str(dset["root"])) / scene).absolute()), "generate": dset.get("generate"),
           "method": mname, "strategy": method["strategy"],
           "options": copy.deepcopy(method.get("options") or {}),
           # copies: an axis set below (splat.fit.*) must not reach the next job's dicts
           "protocol": copy.deepcopy({**sweep.protocol, **(method.get("protocol") or {})}),
           "splat": copy.deepcopy({**sweep.splat, **(method.get("splat") or {})}),
           "seed": seed, "renders": int(sweep.job["renders"]),
           "uncertainty": copy.deepcopy(sweep.uncertainty) if sweep.job["kind"] == "uncertainty" else None}
    for key, value in axes.items():
        _set_dotted(job, key, value)
    job["axes"] = axes
    job["setting"] = ", ".join(f"{k}={v}" for k, v in axes.items())
    job_world = (world_section(method["world"], f"method.{mname}.world") if method.get("world")
                 else sweep.world)
    if job_world is not None:  # part of what the job computes (absent for the pool)
        job["world"] = copy.deepcopy(job_world)
    if dset.get("masks"):  # train and evaluate on the capture's masked-in pixels only
        job["masks"] = True
    if dset.get("up") is not None and "up" not in (method.get("protocol") or {}):
        job["protocol"]["up"] = dset["up"]  # the scene's up axis (absent when unset: hashes as before)
    return job


def _execution(sweep: SweepSections, hash_: str) -> dict:
    """How and where the job runs (not hashed)."""
    job_cfg = sweep.job
    return {"threads": int(job_cfg["threads"]), "device": str(job_cfg["device"]),
            "retries": int(job_cfg["retries"]),
            # images only go to MLflow: none to make without it
            "round_images": int(job_cfg.get("round_images") or 0) if sweep.tracked else 0,
            "round_models": bool(job_cfg.get("round_models") or False),
            "progress_seconds": float(job_cfg.get("progress_seconds", 30)),
            "job_dir": str(SweepFolder(sweep.output_dir).job(hash_).path)}
