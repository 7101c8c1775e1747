"""The config schema: which typed record declares each section of a composed config, and the one
check derived from those declarations (``pipeline.bounds``).

The core's typed configs declare their own fields (``FitConfig`` for ``splat.fit``,
``ProtocolConfig`` for ``protocol``, each strategy's dataclass for ``method.<name>.options``,
``UncertaintyConfig``, ``GeneratedScene`` for a generated dataset); the sections that only the
orchestration reads (``job``, ``executor``, ``tracking``, the top level) are declared here, their
defaults equal to ``conf/`` (a test keeps the two equal). ``config_problems`` walks a composed
config against all of them and returns one line per bad value, before any job is built;
``config_warnings`` the allowed values far above anything measured (``plan=true`` prints them);
``schema_rows`` the same declarations as documentation (``gopre-run --help`` and ``conf/SCHEMA.md``).
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import Iterator

from pipeline.active.config import EpisodeConfig
from pipeline.active.uncertainty import UncertaintyConfig
from pipeline.bounds import (BOOL, FLOAT, INT, STR, Bound, bound_of, bounded, declared, present, problem_lines,
                             violations, warning_lines, warnings)
from pipeline.data.protocols import ProtocolConfig
from pipeline.data.synthetic import GeneratedScene
from pipeline.experiment.executors.config import SECTIONS
from pipeline.fit.config import DensifyConfig, FitConfig

JOB_KINDS = ("episode", "uncertainty")
DEVICES = ("cpu", "cuda")
# MLflow's stores: a local path (no scheme), a file: URI, a server, a database, Databricks
TRACKING_URI = (r"(file:.*|https?://.+|(sqlite|postgresql|mysql|mssql)(\+\w+)?://.+|databricks(://.*)?"
                r"|[^:]+)")


@dataclass(frozen=True)
class Sweep:
    """The top level of ``conf/config.yaml``."""

    name: str = bounded("default", STR, pattern=r"[^/\\]+", pattern_hint="a folder name: no slash")
    plan: bool = bounded(False, BOOL)
    tracking_sync: bool = bounded(False, BOOL)
    validate_images: bool = bounded(True, BOOL)


@dataclass(frozen=True)
class JobSection:
    """``job``: how each job runs (not what it computes)."""

    kind: str = bounded("episode", STR, choices=JOB_KINDS)
    retries: int = bounded(1, INT, ge=0, le=100)          # re-runs of a job that raised (transient errors)
    renders: int = bounded(4, INT, ge=0, le=10_000)
    round_images: int = bounded(2, INT, ge=0, le=10_000)
    round_models: bool = bounded(False, BOOL)
    threads: int = bounded(1, INT, ge=1, le=4096)
    progress_seconds: float = bounded(30, FLOAT, gt=0)
    device: str = bounded("cpu", STR, choices=DEVICES)


EXECUTORS = SECTIONS  # kind -> the ``executor`` section's dataclass, registered beside its class


@dataclass(frozen=True)
class TrackingSection:
    kind: str = bounded("mlflow", STR, choices=("mlflow", "none"))
    uri: str | None = bounded(None, STR, nullable=True, pattern=TRACKING_URI,
                              pattern_hint="a path, file:, http(s)://, sqlite/postgresql/mysql/mssql:// or "
                                           "databricks")
    # a sweep whose jobs could not be tracked (the server away) tries the replay again this long
    # before it ends (experiment.replay); the next launch replays what is still missing
    replay_wait_s: float = bounded(120.0, FLOAT, ge=0)


# The episode's settings: every declared field of ``EpisodeConfig`` but those a sweep sets through
# other keys (the seed: ``seeds``; the world: ``world``; masks: the dataset's). Declared once, on the
# typed config: a new bounded field there is a new ``splat.<name>`` key, checked, documented, planned.
EPISODE_SET_ELSEWHERE = ("seed", "world", "masks")
EPISODE_SETTINGS = tuple(f.name for f in fields(EpisodeConfig)
                         if bound_of(f) is not None and f.name not in EPISODE_SET_ELSEWHERE)
# ``splat.*`` keys that set a typed config's field (null: the preset's value); "all" for
# ``curve_test_views`` means every test view
SPLAT_FIELDS = {"iterations": (FitConfig, "iterations"), "image_width": (FitConfig, "image_width"),
                "max_gaussians": (DensifyConfig, "max_gaussians"),
                **{name: (EpisodeConfig, name) for name in EPISODE_SETTINGS}}


# FitConfig fields a sweep sets through other keys: ``splat.iterations`` (it rescales every schedule)
# and ``seeds`` (each job's seed)
FIT_SET_ELSEWHERE = ("iterations", "seed")


def field_bound(cls, name: str) -> Bound:
    bound = bound_of(next(f for f in fields(cls) if f.name == name))
    if bound is None:
        raise ValueError(f"{cls.__name__}.{name} declares no bound")
    return bound


def splat_bound(key: str) -> Bound:
    """The bound of ``splat.<key>``: its typed field's, null allowed (the preset's value), and
    "all" for ``curve_test_views`` (every test view)."""
    cls, name = SPLAT_FIELDS[key]
    return replace(field_bound(cls, name), nullable=True, also=("all",) if key == "curve_test_views" else ())


def splat_items(splat: dict):
    """(dotted key, bound, value) of every declared value of a splat section, its fit overrides too."""
    yield from ((f"splat.{key}", splat_bound(key), splat[key]) for key in SPLAT_FIELDS if key in splat)
    yield from present(FitConfig, splat.get("fit") or {}, "splat.fit.")


def splat_problems(splat: dict) -> list[str]:
    """One line per bad value of a splat section (the composed config's, or a job's with its axes)."""
    return problem_lines(splat_items(splat))


def sections(cfg: dict) -> Iterator[tuple[str, type, dict]]:
    """(dotted prefix, declaring class, the section's plain data) for every declared section."""
    from pipeline.acquisition.discovery import resolve_strategy
    yield "", Sweep, {k: v for k, v in cfg.items() if not isinstance(v, (dict, list))}
    yield "job.", JobSection, cfg.get("job") or {}
    yield "uncertainty.", UncertaintyConfig, cfg.get("uncertainty") or {}
    yield "protocol.", ProtocolConfig, cfg.get("protocol") or {}
    executor = cfg.get("executor") or {}
    if executor.get("kind") in EXECUTORS:
        yield "executor.", EXECUTORS[executor["kind"]], executor
    yield "tracking.", TrackingSection, cfg.get("tracking") or {}
    for dname, dset in (cfg.get("dataset") or {}).items():
        if isinstance(dset, dict) and isinstance(dset.get("generate"), dict):
            yield f"dataset.{dname}.generate.", GeneratedScene, dset["generate"]
    for mname, method in (cfg.get("method") or {}).items():
        if not isinstance(method, dict):
            continue
        try:
            cls = resolve_strategy(str(method.get("strategy"))).cls
        except ValueError:
            continue  # an unknown strategy has its own error (resolution.strategy_plugins)
        if isinstance(method.get("options"), dict) and hasattr(cls, "__dataclass_fields__"):
            yield f"method.{mname}.options.", cls, method["options"]
        if isinstance(method.get("protocol"), dict):
            yield f"method.{mname}.protocol.", ProtocolConfig, method["protocol"]


def config_problems(cfg: dict) -> list[str]:
    """One line per value of the composed config (plain data) that breaks its declared bound."""
    out = []
    for prefix, cls, data in sections(cfg):
        out += violations(cls, data, prefix)
    if (cfg.get("executor") or {}).get("kind") not in EXECUTORS:
        out.append(f"executor.kind: {(cfg.get('executor') or {}).get('kind')!r} is not one of {', '.join(EXECUTORS)}")
    return out + splat_problems(cfg.get("splat") or {})


def config_warnings(cfg: dict) -> list[str]:
    """Allowed values above their declared ``usual_max`` (a plan says them before estimating)."""
    out = []
    for prefix, cls, data in sections(cfg):
        out += warnings(cls, data, prefix)
    return out + warning_lines(splat_items(cfg.get("splat") or {}))


def schema_rows() -> list[tuple[str, str, object]]:
    """(key, allowed values, default) of every declared key, for the documentation."""
    from pipeline.acquisition import REGISTRY
    rows = []
    for prefix, cls in [("", Sweep), ("job.", JobSection), ("splat.fit.", FitConfig), ("protocol.", ProtocolConfig),
                        ("uncertainty.", UncertaintyConfig), ("tracking.", TrackingSection),
                        ("dataset.<name>.generate.", GeneratedScene),
                        *[(f"executor.({kind}) ", c) for kind, c in EXECUTORS.items()],
                        *[(f"method.<{name}>.options.", c) for name, c in REGISTRY.items()]]:
        rows += [(prefix + key, bound.describe(), default) for key, bound, default in declared(cls)
                 if not (cls is FitConfig and key in FIT_SET_ELSEWHERE)]
    rows += [(f"splat.{key}", splat_bound(key).describe() + " (null: the preset's)", None) for key in SPLAT_FIELDS]
    return rows


def schema_markdown() -> str:
    """Every declared key as a markdown table (``conf/SCHEMA.md``; ``python -m pipeline.experiment.schema``)."""
    lines = ["# Every configurable value: type, range, default", "",
             "Generated from the declarations (`python -m pipeline.experiment.schema > conf/SCHEMA.md`); a value",
             "outside its range is a config error naming the key before any job starts. `splat.*` keys left null",
             "take the splat preset's value (`conf/splat/<preset>.yaml`).", "",
             "| key | allowed | default |", "|---|---|---|"]
    for key, allowed, default in schema_rows():
        shown = "null" if default is None else str(default).lower() if isinstance(default, bool) else repr(default)
        lines.append(f"| `{key}` | {allowed} | `{shown}` |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    print(schema_markdown(), end="")
