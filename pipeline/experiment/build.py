"""From a composed sweep config to a list of jobs, each a plain JSON-able dict with a config hash.

A sweep expands datasets x scenes x methods x seeds x sweep axes. A job dict has:
``kind, dataset, format, scene, scene_path, generate, method, strategy, options, protocol, splat,
seed, renders, uncertainty, axes, setting`` and an ``execution`` part (threads, device, retries,
job folder) that is not part of the hash: the hash names *what* is computed, not where or how.
Every job is validated here (episode config, strategy options) so bad values fail at start-up.
"""

from __future__ import annotations

import copy
import hashlib
import itertools
import json
from dataclasses import fields
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from pipeline.acquisition import POSE_SCORING, REGISTRY as BUILT_IN, make_strategy, scores_any_pose
from pipeline.acquisition.discovery import StrategyError, check_plugins, resolve_strategy
from pipeline.active.uncertainty import UncertaintyConfig
from pipeline.data.fingerprint import FileDigests, scene_fingerprint
from pipeline.data.images import DataError
from pipeline.bounds import BoundsError
from pipeline.experiment.layout import SweepFolder
from pipeline.experiment.schema import config_problems
from pipeline.experiment.provenance import code_version
from pipeline.experiment.spec import Job
from pipeline.experiment.episode_settings import (SPLAT_KEYS, WORLD_KEYS, ConfigError, check_keys,  # noqa: F401
                                                 episode_config, protocol_config, world_changes, world_section)
from pipeline.experiment.splat_section import job_form

# protocol/splat: overrides for this method; world: this method's capture simulator (gopre_search)
METHOD_KEYS = {"strategy", "options", "protocol", "splat", "world"}
# Part of every job's hash: bumped when a fix changes what the same config computes, so a sweep
# never resumes or reuses results of the code before it. "fidelity-1": the paper-fidelity fixes (scene extent,
# tau -> 0, ActiveNeRF port, prune switch, kNN scales, probes incl. the initial views).
RESULTS_REVISION = "fidelity-1"
NOT_HASHED = ("execution", "scene_path", "sweep", "index", "code_version", "config_hash")


def config_hash(job: dict | Job) -> str:
    """Stable hash of what a job computes (no paths, no execution settings), of its plain form."""
    plain = job.to_dict() if isinstance(job, Job) else job
    core = {k: v for k, v in plain.items() if k not in NOT_HASHED}
    return hashlib.sha256(json.dumps(core, sort_keys=True, default=str).encode()).hexdigest()[:16]


def data_fingerprint(scene_path: str, generate: dict | None, masks: bool, digests: FileDigests) -> str:
    """The scene's data identity for a job's hash (``pipeline.data.fingerprint``): the digest of its
    files; "" for the generated scene, whose generator options the hash holds already (so generated
    sweeps keep their hashes); ``MISSING_DATA`` when the folder cannot be read (the pre-flight check
    then names the problem)."""
    if generate is not None:  # its options are in the hash already (Job.data_identity names them)
        return ""
    try:
        return scene_fingerprint(scene_path, masks, digests).short
    except (DataError, OSError):
        return MISSING_DATA


MISSING_DATA = "unreadable"


def without_data_identity(job: Job) -> str:
    """The hash the same job had before data identity (no fingerprint in it): what a sweep folder
    launched before it recorded."""
    plain = job.to_dict()
    plain.pop("data_fingerprint", None)
    return config_hash(plain)


def _container(cfg: DictConfig, key: str):
    try:
        return OmegaConf.to_container(cfg[key], resolve=True)
    except Exception as err:  # interpolation and resolver errors name the key themselves
        raise ConfigError(f"{key}: {err}") from None


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


def _leaves(tree: dict, prefix: str = "") -> dict[str, object]:
    out = {}
    for key, value in tree.items():
        if isinstance(value, dict):
            out.update(_leaves(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def _axes(cfg: DictConfig) -> list[dict]:
    """Sweep axes: every list leaf of ``sweep`` (nested like the job, e.g. sweep.protocol.probes)."""
    sweep = _leaves(_container(cfg, "sweep") or {})
    for key, values in sweep.items():
        if not isinstance(values, list) or not values:
            raise ConfigError(f"sweep.{key}: expected a non-empty list of values, got {values!r}")
    keys = sorted(sweep)
    return [dict(zip(keys, combo)) for combo in itertools.product(*(sweep[k] for k in keys))]


def seeds_of(cfg: DictConfig) -> list[int]:
    """``seeds``: a list of integers (or one integer); anything else is a config error."""
    value = cfg.get("seeds")
    seeds = _container(cfg, "seeds") if OmegaConf.is_config(value) else value  # a list node, or a scalar
    seeds = [seeds] if isinstance(seeds, int) and not isinstance(seeds, bool) else seeds
    if not isinstance(seeds, list) or not seeds or any(
            isinstance(s, bool) or not isinstance(s, int) for s in seeds):
        raise ConfigError(f"seeds: expected a non-empty list of integers, e.g. seeds=[0,1,2], got {seeds!r}")
    if any(s < 0 for s in seeds):
        raise ConfigError(f"seeds: a seed must be >= 0, got {seeds!r}")
    if len(set(seeds)) != len(seeds):  # each job would run twice and its records be duplicated
        raise ConfigError(f"seeds: {seeds!r} lists a seed twice")
    return seeds


DATASET_KEYS = {"format", "root", "scenes"}


def plain_config(cfg: DictConfig) -> dict:
    """The composed config as plain data, section by section (a bad interpolation names its key)."""
    return {key: _container(cfg, key) if OmegaConf.is_config(cfg[key]) else cfg[key] for key in cfg}


def check_declared(cfg: DictConfig) -> None:
    """Every value against its declared bound (``experiment.schema``): one ConfigError listing every
    bad value, key by key, before any job is built."""
    problems = config_problems(plain_config(cfg))
    if problems:
        raise ConfigError(problems[0] if len(problems) == 1 else
                          f"{len(problems)} bad values, nothing was started:\n  " + "\n  ".join(problems))


def expand_jobs(cfg: DictConfig) -> list[Job]:
    """Every job of the sweep, validated, in a deterministic order."""
    datasets, methods = _container(cfg, "dataset"), _container(cfg, "method")
    protocol, splat, job_cfg = _container(cfg, "protocol"), _container(cfg, "splat"), _container(cfg, "job")
    # a preset's settings for a dataset that the list does not select (e.g. experiment=debug
    # dataset=shared: debug sizes the generated scene) hold none of these keys: not a dataset here
    datasets = {d: v for d, v in (datasets or {}).items() if set(v or {}) & DATASET_KEYS}
    if not datasets:
        raise ConfigError("dataset: no dataset selected")
    if not methods:
        raise ConfigError("method: no method selected")
    check_declared(cfg)
    world = world_section(_container(cfg, "world") or {"kind": "dataset"})
    try:
        splat = job_form(splat)
    except ValueError as err:
        raise ConfigError(f"splat.{err}") from None
    plugins = strategy_plugins(methods)
    jobs, digests, fingerprints = [], FileDigests(), {}
    output_dir = Path(str(cfg.output_dir)).absolute()  # job folders: the same wherever the job runs
    tracked = (_container(cfg, "tracking") or {}).get("kind") == "mlflow"
    for dname, dset in datasets.items():
        missing = sorted(DATASET_KEYS - set(dset))
        if missing:
            raise ConfigError(f"dataset.{dname}: missing keys {missing} (selected: {sorted(datasets)})")
    for (dname, dset), (mname, method), seed, axes in itertools.product(
            datasets.items(), methods.items(), seeds_of(cfg), _axes(cfg)):
        check_keys(f"method.{mname}", method, METHOD_KEYS)
        for scene in dset["scenes"]:
            job = {"sweep": str(cfg.name), "results_revision": RESULTS_REVISION,
                   "kind": job_cfg["kind"], "dataset": dname,
                   "format": dset["format"], "scene": scene,
                   "scene_path": str((Path(str(dset["root"])) / scene).absolute()), "generate": dset.get("generate"),
                   "method": mname, "strategy": method["strategy"],
                   "options": copy.deepcopy(method.get("options") or {}),
                   "protocol": {**protocol, **(method.get("protocol") or {})},
                   "splat": {**splat, **(method.get("splat") or {})},
                   "seed": int(seed), "renders": int(job_cfg["renders"]),
                   "uncertainty": _container(cfg, "uncertainty") if job_cfg["kind"] == "uncertainty" else None}
            for key, value in axes.items():
                _set_dotted(job, key, value)
            job["axes"] = axes
            job["setting"] = ", ".join(f"{k}={v}" for k, v in axes.items())
            job_world = (world_section(method["world"], f"method.{mname}.world") if method.get("world")
                         else world)
            if job_world is not None:  # part of what the job computes (absent for the pool)
                job["world"] = copy.deepcopy(job_world)
            if dset.get("masks"):  # train and evaluate on the capture's masked-in pixels only
                job["masks"] = True
            if dset.get("up") is not None and "up" not in (method.get("protocol") or {}):
                job["protocol"]["up"] = dset["up"]  # the scene's up axis (absent when unset: hashes as before)
            if plugins[mname] is not None:  # the plugin's code is part of what the job computes
                job["plugin"] = plugins[mname]
            data_key = (job["scene_path"], json.dumps(job["generate"], sort_keys=True), bool(job.get("masks")))
            if data_key not in fingerprints:  # each scene's files hashed once per launch (and cached on disk)
                fingerprints[data_key] = data_fingerprint(job["scene_path"], job["generate"], data_key[2], digests)
            if fingerprints[data_key]:  # absent for the generated scene: its hash as before
                job["data_fingerprint"] = fingerprints[data_key]
            job["config_hash"] = config_hash(job)
            job["execution"] = {"threads": int(job_cfg["threads"]), "device": str(job_cfg["device"]),
                                "retries": int(job_cfg["retries"]),
                                # images only go to MLflow: none to make without it
                                "round_images": int(job_cfg.get("round_images") or 0) if tracked else 0,
                                "round_models": bool(job_cfg.get("round_models") or False),
                                "progress_seconds": float(job_cfg.get("progress_seconds", 30)),
                                "job_dir": str(SweepFolder(output_dir).job(job["config_hash"]).path)}
            job["index"] = len(jobs)  # the order the config lists things in (tables keep it)
            job["code_version"] = code_version()
            typed = Job.from_dict(job)
            validate_job(typed)
            jobs.append(typed)
    digests.save()
    return jobs


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


def uncertainty_config(job: Job) -> UncertaintyConfig:
    data = dict(job.uncertainty or {})
    check_keys("uncertainty", data, {f.name for f in fields(UncertaintyConfig)})
    if "methods" in data:
        data["methods"] = tuple(data["methods"])
    return UncertaintyConfig(**data, seed=job.seed)


def validate_job(job: Job) -> None:
    job.episode  # resolved once here, at start-up; a bad value is a config error naming the key
    try:
        strategy = make_strategy(job.strategy, **job.options)
    except BoundsError as err:
        raise ConfigError(err.under(f"method.{job.method}.options.")) from None
    except ValueError as err:
        raise ConfigError(f"method.{job.method}: {err}") from None
    if job.world is not None and not scores_any_pose(strategy):
        raise ConfigError(f"method.{job.method}: world={job.world['kind']} searches poses off the pool, which "
                          f"needs a strategy that scores any camera ({', '.join(POSE_SCORING)}); {job.strategy!r} "
                          "picks from the pool only")
    if job.kind == "uncertainty":
        uncertainty_config(job)
