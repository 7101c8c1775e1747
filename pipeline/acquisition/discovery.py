"""Where a strategy comes from: a built-in name, an installed plugin, or a dotted path.

A method YAML's ``strategy`` is resolved here, once, into a class and its identity:

- a built-in name (``gopre``, ``random``, ...): ``BUILT_IN``, part of this package;
- an entry point of the group ``gopre.strategies`` (``name = package.module:Class`` in the plugin
  distribution's ``pyproject.toml``), found with ``importlib.metadata``, the way nerfstudio finds
  ``nerfstudio.method_configs`` and NerfBaselines ``nerfbaselines.specs``;
- a dotted path ``package.module:Class`` (the module importable from the Python path).

A plugin is refused with one line naming its entry point or path when it cannot be imported, is not
a class or lacks the protocol's ``select`` method. An entry point that reuses a built-in name refuses
every launch that asks for that name (neither would be a safe guess) and is warned about otherwise.
Its identity (the distribution's name and version, and a sha256 of its module's source) is part
of every job that runs it, so a changed plugin is re-run, never "already finished".
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.metadata as metadata
import inspect
from dataclasses import asdict, dataclass
from pathlib import Path
from pipeline.acquisition.registry import REGISTRY

ENTRY_POINT_GROUP = "gopre.strategies"


class StrategyError(ValueError):
    """A strategy that cannot be found, imported or used; the message is one line naming it."""


@dataclass(frozen=True)
class StrategySource:
    """A strategy class and where it came from. ``plugin`` is None for a built-in."""

    name: str                         # what the method YAML said
    cls: type
    plugin: "PluginIdentity | None"


@dataclass(frozen=True)
class PluginIdentity:
    """What identifies a plugin's code in a job's hash, its records and its MLflow tags."""

    reference: str                    # the entry point ``name = value`` or the dotted path
    distribution: str | None          # the installed distribution that provides it (None: a bare path)
    version: str | None
    source_sha256: str                # of the class's module source (the whole package's for a package)

    def to_dict(self) -> dict:
        return asdict(self)


def _built_in() -> dict[str, type]:
    return REGISTRY


def strategy_entry_points() -> dict[str, metadata.EntryPoint]:
    """The installed ``gopre.strategies`` entry points by name."""
    return {ep.name: ep for ep in metadata.entry_points(group=ENTRY_POINT_GROUP)}


def is_dotted_path(name: str) -> bool:
    return ":" in name


def resolve_strategy(name: str) -> StrategySource:
    """The class a method's ``strategy`` names, with its identity; ``StrategyError`` otherwise."""
    if not isinstance(name, str) or not name:
        raise StrategyError(f"strategy: expected a name or package.module:Class, got {name!r}")
    built_in = _built_in()
    if name in built_in:
        clash = shadowing_entry_points().get(name)
        if clash is not None:  # which of the two would run is not the user's to guess
            raise StrategyError(clash)
        return StrategySource(name, built_in[name], None)
    if is_dotted_path(name):
        cls = _load(name, f"strategy {name!r}", lambda: _import_path(name))
        return StrategySource(name, cls, _identity(name, cls, None))
    points = strategy_entry_points()
    if name in points:
        ep = points[name]
        where = f"entry point {ENTRY_POINT_GROUP}:{ep.name} = {ep.value}" + (
            f" (from {ep.dist.name} {ep.dist.version})" if ep.dist is not None else "")
        cls = _load(name, where, ep.load)
        return StrategySource(name, cls, _identity(f"{ep.name} = {ep.value}", cls, ep.dist))
    raise StrategyError(f"unknown strategy {name!r}; built-in: {sorted(built_in)}; installed plugins "
                        f"({ENTRY_POINT_GROUP}): {sorted(points) or 'none'}; or give package.module:Class")


def shadowing_entry_points() -> dict[str, str]:
    """Installed entry points that reuse a built-in name: name -> the line that says so."""
    built_in, out = _built_in(), {}
    for ep in strategy_entry_points().values():
        if ep.name in built_in:
            dist = f" (from {ep.dist.name} {ep.dist.version})" if ep.dist is not None else ""
            out[ep.name] = (f"entry point {ENTRY_POINT_GROUP}:{ep.name} = {ep.value}{dist} reuses the "
                            f"built-in strategy name {ep.name!r}; rename it in the plugin's pyproject.toml")
    return out


_WARNED: set[str] = set()


def check_plugins(used: set[str] | frozenset[str] = frozenset(), warn=None) -> None:
    """An installed entry point that reuses a built-in name refuses the launches that use that name
    (``used``: the strategies of the launch; one line naming it), so a shadowing plugin never
    silently loses to the built-in; any other launch goes on, and ``warn`` hears each clash once per
    process."""
    for name, line in shadowing_entry_points().items():
        if name in used:
            raise StrategyError(line)
        if warn is not None and line not in _WARNED:
            _WARNED.add(line)
            warn(f"warning: {line} (strategy {name!r} is refused until then; this launch does not use it)")


def _import_path(path: str):
    module_name, _, attr = path.partition(":")
    module = importlib.import_module(module_name)
    obj = module
    for part in attr.split("."):
        obj = getattr(obj, part)
    return obj


def _load(name: str, where: str, load) -> type:
    try:
        cls = load()
    except Exception as err:  # an ImportError, AttributeError or anything the plugin's import raised
        raise StrategyError(f"{where}: cannot be imported ({type(err).__name__}: {err})") from None
    if not inspect.isclass(cls):
        raise StrategyError(f"{where}: is a {type(cls).__name__}, not a strategy class")
    if not callable(getattr(cls, "select", None)):
        raise StrategyError(f"{where}: {cls.__qualname__} has no select(ctx, count) method "
                            "(see pipeline.api.Strategy)")
    params = list(inspect.signature(cls.select).parameters)
    if len(params) < 3:  # self, ctx, count
        raise StrategyError(f"{where}: {cls.__qualname__}.select takes {params}; the protocol is "
                            "select(self, ctx, count=1) (see pipeline.api.Strategy)")
    return cls


def _identity(reference: str, cls: type, dist) -> PluginIdentity:
    return PluginIdentity(reference, dist.name if dist is not None else None,
                          dist.version if dist is not None else None, source_sha256(cls))


def source_sha256(cls: type) -> str:
    """sha256 of the source a class comes from: every ``.py`` file of its top-level package
    (sorted by path), or its module's file when it is a bare module."""
    module = inspect.getmodule(cls)
    file = Path(inspect.getfile(module))
    top = importlib.import_module(cls.__module__.split(".")[0])
    top_file = Path(getattr(top, "__file__", "") or file)
    files = sorted(top_file.parent.rglob("*.py")) if top_file.name == "__init__.py" else [file]
    digest = hashlib.sha256()
    for path in files:
        digest.update(str(path.relative_to(top_file.parent)).encode() + b"\0" + path.read_bytes() + b"\0")
    return digest.hexdigest()
