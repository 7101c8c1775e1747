"""Acquisition strategies behind one protocol: the built-ins in an explicit registry (``registry``); strategies
from outside the package through ``discovery`` (entry points ``gopre.strategies`` or a dotted path)."""

from pipeline.acquisition.base import Selection, SelectionContext, Strategy
from pipeline.acquisition.discovery import resolve_strategy
from pipeline.acquisition.registry import REGISTRY


# the strategies that score any camera (pose_scorer), so a search over poses can use them
POSE_SCORING = tuple(name for name, cls in REGISTRY.items() if hasattr(cls, "pose_scorer"))


def make_strategy(name: str, **options) -> Strategy:
    """Build a strategy by built-in name, installed plugin name (entry point group
    ``gopre.strategies``) or ``package.module:Class`` (``discovery.resolve_strategy``); unknown
    names, plugins that cannot load, and bad options fail with a clear one-line error."""
    cls = resolve_strategy(name).cls
    try:
        return cls(**options)
    except TypeError as err:
        raise ValueError(f"strategy {name!r}: bad options {sorted(options)} ({err})") from None


def scores_any_pose(strategy) -> bool:
    """Whether a strategy can score a camera off the pool (it has ``pose_scorer``)."""
    return callable(getattr(strategy, "pose_scorer", None))


__all__ = ["POSE_SCORING", "REGISTRY", "Selection", "SelectionContext", "Strategy", "make_strategy"]
