"""A job's episode settings as the core's plain ``EpisodeConfig``: the splat section's keys over a
preset, the protocol and the world, checked with errors that name the key. No Hydra here: ``Job``
(``spec``) resolves its episode with ``episode_config``; ``resolution`` makes the jobs."""

from __future__ import annotations

from dataclasses import fields, replace
from pathlib import Path
from typing import TYPE_CHECKING

from pipeline.active.config import EpisodeConfig, episode_preset
from pipeline.active.uncertainty import UncertaintyConfig
from pipeline.bounds import under
from pipeline.data.protocols import ProtocolConfig
from pipeline.experiment.schema import EPISODE_SETTINGS, SPLAT_FIELDS, splat_problems

if TYPE_CHECKING:
    from pipeline.experiment.spec import Job

SPLAT_KEYS = {"preset", "init", "fit", *SPLAT_FIELDS}
# init (+splat.init=ply:PATH), reset_recovery (+splat.reset_recovery=N) and densify_settle
# (+splat.densify_settle=N) are optional; fit (conf/splat/<preset>.yaml lists the recipe, e.g.
# splat.fit.lr.means_init=1e-4) reaches a job as what differs from the preset (splat_section.job_form),
# so the presets' hashes do not change; `gopre-run ... plan=true` lists every hyperparameter a job runs with.


class ConfigError(ValueError):
    """A sweep config that cannot run; the message names the key."""


def check_keys(section: str, data: dict, allowed: set[str]) -> None:
    unknown = set(data) - allowed
    if unknown:
        raise ConfigError(f"{section}: unknown keys {sorted(unknown)}; allowed {sorted(allowed)}")


def episode_config(job: Job) -> EpisodeConfig:
    """The core's plain dataclass for a job (the core never sees a DictConfig)."""
    splat = dict(job.splat)
    check_keys("splat", splat, SPLAT_KEYS)
    problems = splat_problems(splat)  # a sweep axis's values too (0 is not "unset": 0 iterations would
    if problems:                      # silently mean the preset's)
        raise ConfigError("; ".join(problems))
    try:
        base = episode_preset(splat["preset"])
        fit = base.fit
        if splat.get("iterations"):
            fit = fit.scaled_to(int(splat["iterations"]))
        if splat.get("image_width"):
            fit = fit.with_changes(image_width=int(splat["image_width"]))
        if splat.get("max_gaussians"):
            fit = fit.with_changes(densify=replace(fit.densify, max_gaussians=int(splat["max_gaussians"])))
    except (ValueError, TypeError) as err:
        raise ConfigError(under(err, "splat.")) from None
    if splat.get("fit"):
        try:
            fit = fit.with_overrides(dict(splat["fit"]))
        except ValueError as err:
            raise ConfigError(under(err, "splat.fit.")) from None
    fit = fit.with_changes(seed=job.seed)
    protocol = protocol_config(job.protocol)
    changes = {k: splat[k] for k in (*EPISODE_SETTINGS, "init") if splat.get(k) is not None}
    if changes.get("curve_test_views") == "all":  # null keeps the preset's curve subset
        changes["curve_test_views"] = None
    changes.update(world_changes(job.world))
    try:
        return replace(base, fit=fit, protocol=protocol, strategy=job.strategy,
                       strategy_options=dict(job.options), seed=job.seed, masks=bool(job.masks), **changes)
    except (ValueError, TypeError) as err:  # EpisodeConfig's fields are the splat section's keys
        raise ConfigError(under(err, "splat.")) from None


def uncertainty_config(job: Job) -> UncertaintyConfig:
    """The core's uncertainty-experiment config of an uncertainty job."""
    data = dict(job.uncertainty or {})
    check_keys("uncertainty", data, {f.name for f in fields(UncertaintyConfig)})
    if "methods" in data:
        data["methods"] = tuple(data["methods"])
    return UncertaintyConfig(**data, seed=job.seed)


WORLD_KEYS = {"kind", "model", "search"}


def world_section(data: dict, where: str = "world") -> dict | None:
    """The ``world`` section (at ``where``): None for the dataset's pool, else checked, as plain data."""
    check_keys(where, data, WORLD_KEYS)
    if data.get("kind", "dataset") == "dataset":
        if data.get("model") is not None or data.get("search"):
            raise ConfigError(f"{where}: model and search need a capture simulator (world=generated or twin)")
        return None
    if data["kind"] == "twin":
        model = data.get("model")
        if not (isinstance(model, str) and model.startswith("ply:")):
            raise ConfigError(f"{where}.model: world=twin needs the reference splat as ply:PATH, got {model!r}")
        if not Path(model[len("ply:"):]).is_file():
            raise ConfigError(f"{where}.model: {model[len('ply:'):]}: no such file (make the scene's twin with "
                              f"`gopre-data twin SCENE_FOLDER {model[len('ply:'):]}`)")
    return {k: v for k, v in data.items() if v is not None}


def world_changes(world: dict | None) -> dict:
    """The EpisodeConfig fields of a job's world (none for the pool)."""
    if world is None:
        return {}
    return {"world": world["kind"], "world_model": world.get("model"), "search": dict(world.get("search") or {})}


def protocol_config(data: dict) -> ProtocolConfig:
    check_keys("protocol", data, {f.name for f in fields(ProtocolConfig)})
    try:
        return ProtocolConfig(**data)
    except ValueError as err:
        raise ConfigError(under(err, "protocol.")) from None
