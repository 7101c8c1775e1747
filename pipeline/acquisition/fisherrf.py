"""``fisherrf``: FisherRF as released, score = sum_i F_x,i / (H_train,i + lambda), argmax.

FisherRF's parameter set omits rotations (``quats``); the Fisher here is exact (channels
squared separately), unlike the released CUDA kernel (see design notes)."""

from __future__ import annotations

from dataclasses import dataclass

from pipeline.acquisition.base import (Selection, SelectionContext, greedy_pick, pool_and_train_fishers,
                                       timed_selection)
from pipeline.fisher.exact import FisherSpec

FISHERRF_GROUPS = ("means", "log_scales", "logit_opacities", "sh0", "shN")


@dataclass
class FisherRFStrategy:
    name: str = "fisherrf"
    lam: float = 1e-6
    spec: FisherSpec = FisherSpec(groups=FISHERRF_GROUPS)

    def select(self, ctx: SelectionContext, count: int = 1) -> Selection:
        def run(order):
            cands, h = pool_and_train_fishers(ctx, order, self.spec)
            return greedy_pick(cands, h, lambda h_, f: (f / (h_ + self.lam)).sum(-1), count, True)
        return timed_selection(ctx, run)
