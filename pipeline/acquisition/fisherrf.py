"""``fisherrf``: FisherRF, score = sum_i F_x,i / (H_train,i + lambda), argmax; a greedy batch adds
each pick's F to H_train.

FisherRF's parameter set omits rotations (``quats``). ``hessian="exact"`` (default) uses the exact
diagonal Fisher (channels squared separately); ``hessian="fisherrf_released"`` the released CUDA
kernel's Hessian (channel-summed derivative squared, activations applied once; see
``FisherSpec``). The method preset ``fisherrf_released`` pairs it with the released code's model
reload after every pick (``splat.post_selection=reload``)."""

from __future__ import annotations

from dataclasses import dataclass, field

from torch import Tensor

from pipeline.bounds import FLOAT, STR, bounded, require_bounds
from pipeline.acquisition.base import (PoseScorer, Selection, SelectionContext, gain_pose_scorer, greedy_pick,
                                       pool_and_train_fishers, timed_selection)
from pipeline.fisher.exact import HESSIANS, FisherSpec
from pipeline.fisher.posterior import POSTERIOR_LAMBDA

FISHERRF_GROUPS = ("means", "log_scales", "logit_opacities", "sh0", "shN")


@dataclass
class FisherRFStrategy:
    name: str = "fisherrf"
    lam: float = bounded(POSTERIOR_LAMBDA, FLOAT, gt=0)
    hessian: str = bounded("exact", STR, choices=HESSIANS)
    spec: FisherSpec = field(init=False)

    def __post_init__(self) -> None:
        require_bounds(self)
        self.spec = FisherSpec(groups=FISHERRF_GROUPS, hessian=self.hessian)

    def information_gain(self, h: Tensor, fishers: Tensor) -> Tensor:
        """sum_i F_x,i / (H_i + lambda) of each view: h [D], fishers [M, D] -> [M] (the higher the better)."""
        return (fishers / (h + self.lam)).sum(-1)

    def select(self, ctx: SelectionContext, count: int = 1) -> Selection:
        def run(order):
            cands, h = pool_and_train_fishers(ctx, order, self.spec)
            return greedy_pick(cands, h, self.information_gain, count, True)
        return timed_selection(ctx, run)

    def pose_scorer(self, ctx: SelectionContext) -> PoseScorer:
        """The information gain of any cameras, negated (a search minimises it)."""
        return gain_pose_scorer(ctx, self.spec, self.information_gain)
