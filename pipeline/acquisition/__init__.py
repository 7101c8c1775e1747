"""Acquisition strategies behind one protocol, with an explicit registry (no import magic)."""

from pipeline.acquisition.activenerf import ActiveNeRFStrategy
from pipeline.acquisition.base import Selection, SelectionContext, Strategy
from pipeline.acquisition.cover import CoverStrategy
from pipeline.acquisition.coverage import CoverageStrategy
from pipeline.acquisition.fisherrf import FisherRFStrategy
from pipeline.acquisition.gaussmi import GaussMIStrategy
from pipeline.acquisition.gopre import GoPreStrategy
from pipeline.acquisition.popgs import PopGSStrategy
from pipeline.acquisition.random import RandomStrategy

REGISTRY = {
    "random": RandomStrategy,
    "coverage": CoverageStrategy,
    "cover": CoverStrategy,
    "fisherrf": FisherRFStrategy,
    "popgs": PopGSStrategy,
    "gopre": GoPreStrategy,
    "activenerf": ActiveNeRFStrategy,
    "gaussmi": GaussMIStrategy,
}


# the strategies that score any camera (pose_scorer), so a search over poses can use them
POSE_SCORING = tuple(name for name, cls in REGISTRY.items() if hasattr(cls, "pose_scorer"))


def make_strategy(name: str, **options) -> Strategy:
    """Build a strategy by registry key; unknown names or options fail with a clear error."""
    if name not in REGISTRY:
        raise ValueError(f"unknown strategy {name!r}; available: {sorted(REGISTRY)}")
    try:
        return REGISTRY[name](**options)
    except TypeError as err:
        raise ValueError(f"strategy {name!r}: bad options {sorted(options)} ({err})") from None


__all__ = ["POSE_SCORING", "REGISTRY", "Selection", "SelectionContext", "Strategy", "make_strategy"]
