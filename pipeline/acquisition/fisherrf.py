"""``fisherrf``: FisherRF, score = sum_i F_x,i / (H_train,i + lambda), argmax; a greedy batch adds
each pick's F to H_train.

FisherRF's parameter set omits rotations (``quats``). ``hessian="exact"`` (default) uses the exact
diagonal Fisher (channels squared separately); ``hessian="fisherrf_released"`` the released CUDA
kernel's Hessian (channel-summed derivative squared, activations applied once; see
``FisherSpec``). The method preset ``fisherrf_released`` pairs it with the released code's model
reload after every pick (``splat.post_selection=reload``)."""

from __future__ import annotations

from dataclasses import dataclass, field

from pipeline.acquisition.base import (Selection, SelectionContext, greedy_pick, pool_and_train_fishers,
                                       timed_selection)
from pipeline.fisher.exact import FisherSpec
from pipeline.fisher.posterior import POSTERIOR_LAMBDA

FISHERRF_GROUPS = ("means", "log_scales", "logit_opacities", "sh0", "shN")


@dataclass
class FisherRFStrategy:
    name: str = "fisherrf"
    lam: float = POSTERIOR_LAMBDA
    hessian: str = "exact"
    spec: FisherSpec = field(init=False)

    def __post_init__(self) -> None:
        self.spec = FisherSpec(groups=FISHERRF_GROUPS, hessian=self.hessian)

    def select(self, ctx: SelectionContext, count: int = 1) -> Selection:
        def run(order):
            cands, h = pool_and_train_fishers(ctx, order, self.spec)
            return greedy_pick(cands, h, lambda h_, f: (f / (h_ + self.lam)).sum(-1), count, True)
        return timed_selection(ctx, run)
