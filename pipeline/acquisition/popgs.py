"""``popgs``: POp-GS D-optimality, diagonal variant:
score = log det(Sigma^-1 + F_x) - log det(Sigma^-1) = sum_i log1p(F_x,i / (H_i + lambda)), argmax."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from pipeline.acquisition.base import (Selection, SelectionContext, fisher_vectors, greedy_pick,
                                       timed_selection)
from pipeline.fisher.exact import FisherSpec


@dataclass
class PopGSStrategy:
    name: str = "popgs"
    lam: float = 1e-6
    spec: FisherSpec = FisherSpec()

    def select(self, ctx: SelectionContext, count: int = 1) -> Selection:
        def run(order):
            cands = fisher_vectors(ctx, ctx.candidates[order], self.spec)
            h = fisher_vectors(ctx, ctx.taken, self.spec).sum(0) if len(ctx.taken) else cands[0] * 0
            return greedy_pick(cands, h, lambda h_, f: torch.log1p(f / (h_ + self.lam)).sum(-1),
                               count, True)
        return timed_selection(ctx, run)
