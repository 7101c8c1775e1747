"""The built-in strategies by name: the table ``make_strategy`` and ``discovery`` resolve names
against (a plugin's name never replaces one of these)."""

from pipeline.acquisition.activenerf import ActiveNeRFStrategy
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
