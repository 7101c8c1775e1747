"""``coverage``: the candidate farthest from every taken view (greedy farthest-point on camera
centres), a strong cheap baseline; the score is that distance."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from pipeline.acquisition.base import Selection, SelectionContext, timed_selection


@dataclass
class CoverageStrategy:
    name: str = "coverage"

    def select(self, ctx: SelectionContext, count: int = 1) -> Selection:
        def run(order):
            pool = ctx.candidates.centers[order].double()  # [M, 3]
            taken = ctx.taken.centers.double()
            nearest = (torch.cdist(pool, taken).min(1).values if len(taken)
                       else torch.full((len(order),), torch.inf, dtype=torch.float64))
            first, picks = nearest.clone(), []
            for _ in range(min(count, len(order))):
                best = int(torch.argmax(nearest))
                picks.append(best)
                nearest = torch.minimum(nearest, (pool - pool[best]).norm(dim=1))
                nearest[best] = -torch.inf
            return picks, first
        return timed_selection(ctx, run)
