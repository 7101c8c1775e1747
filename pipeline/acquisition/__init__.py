"""Acquisition strategies behind one protocol: the built-ins in an explicit registry; strategies
from outside the package through ``discovery`` (entry points ``gopre.strategies`` or a dotted path)."""

from pipeline.acquisition.activenerf import ActiveNeRFStrategy
from pipeline.acquisition.base import Selection, SelectionContext, Strategy
from pipeline.acquisition.cover import CoverStrategy
from pipeline.acquisition.coverage import CoverageStrategy
from pipeline.acquisition.fisherrf import FisherRFStrategy
from pipeline.acquisition.fisherrf_nbvgym import FisherRFNbvGymStrategy
from pipeline.acquisition.gaussmi import GaussMIStrategy
from pipeline.acquisition.gopre import GoPreStrategy
from pipeline.acquisition.popgs import PopGSStrategy
from pipeline.acquisition.random import RandomStrategy
from pipeline.acquisition.warprf import WarpRFStrategy

REGISTRY = {
    "random": RandomStrategy,
    "coverage": CoverageStrategy,
    "cover": CoverStrategy,
    "fisherrf": FisherRFStrategy,
    "popgs": PopGSStrategy,
    "gopre": GoPreStrategy,
    "activenerf": ActiveNeRFStrategy,
    "gaussmi": GaussMIStrategy,
    "warprf": WarpRFStrategy,
    "fisherrf_nbvgym": FisherRFNbvGymStrategy,
}


# the strategies that score any camera (pose_scorer), so a search over poses can use them
POSE_SCORING = tuple(name for name, cls in REGISTRY.items() if hasattr(cls, "pose_scorer"))


def make_strategy(name: str, **options) -> Strategy:
    """Build a strategy by built-in name, installed plugin name (entry point group
    ``gopre.strategies``) or ``package.module:Class`` (``discovery.resolve_strategy``); unknown
    names, plugins that cannot load, and bad options fail with a clear one-line error."""
    from pipeline.acquisition.discovery import resolve_strategy
    cls = resolve_strategy(name).cls
    try:
        return cls(**options)
    except TypeError as err:
        raise ValueError(f"strategy {name!r}: bad options {sorted(options)} ({err})") from None


def scores_any_pose(strategy) -> bool:
    """Whether a strategy can score a camera off the pool (it has ``pose_scorer``)."""
    return callable(getattr(strategy, "pose_scorer", None))


__all__ = ["POSE_SCORING", "REGISTRY", "Selection", "SelectionContext", "Strategy", "make_strategy"]
