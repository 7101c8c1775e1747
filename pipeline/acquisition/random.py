"""``random``: a fresh seeded uniform draw each round (POp-GS's protocol), or FisherRF's
reshuffle with the same seed every round (``same_seed_each_round=True``)."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from pipeline.bounds import BOOL, INT, bounded, require_bounds
from pipeline.acquisition.base import Selection, SelectionContext, timed_selection


@dataclass
class RandomStrategy:
    name: str = "random"
    same_seed_each_round: bool = bounded(False, BOOL)
    seed: int = bounded(0, INT, ge=0)

    def __post_init__(self) -> None:
        require_bounds(self)

    def select(self, ctx: SelectionContext, count: int = 1) -> Selection:
        gen = torch.Generator().manual_seed(self.seed) if self.same_seed_each_round else ctx.generator

        def run(order):
            perm = torch.randperm(len(order), generator=gen)
            scores = torch.empty(len(order))
            scores[perm] = torch.arange(len(order), 0, -1, dtype=torch.float32)  # draw rank
            return perm[:count].tolist(), scores
        return timed_selection(ctx, run)
