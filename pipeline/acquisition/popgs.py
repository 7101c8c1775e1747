"""``popgs``: POp-GS D-optimality, argmax of the log-det information gain.

- ``variant="diag"``: sum_i log1p(F_x,i / (H_i + lambda)).
- ``variant="block"``: one dense block per Gaussian over ``block_spec`` parameters,
  sum_g log det(I + Sigma_g^1/2 F_x,g Sigma_g^1/2) with F_x,g = A^T G A built from the
  per-channel feature gradients; by Sylvester's identity computed as log det(I_9 + G A Sigma_g A^T).
  Candidate blocks are streamed (never stored), so memory stays at one view's factors.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from torch import Tensor

from pipeline.bounds import FLOAT, STR, bounded, require_bounds
from pipeline.acquisition.base import (PoseScorer, Selection, SelectionContext, gain_pose_scorer, greedy_pick,
                                       pool_and_train_fishers, timed_selection)
from pipeline.cameras import Cameras
from pipeline.fisher.exact import FisherSpec, view_factors
from pipeline.fisher.posterior import POSTERIOR_LAMBDA

BLOCK_GROUPS = ("means", "log_scales", "quats", "logit_opacities", "sh0")
VARIANTS = ("diag", "block")


@dataclass
class PopGSStrategy:
    name: str = "popgs"
    lam: float = bounded(POSTERIOR_LAMBDA, FLOAT, gt=0)
    variant: str = bounded("diag", STR, choices=VARIANTS)
    spec: FisherSpec = FisherSpec()
    block_spec: FisherSpec = FisherSpec(groups=BLOCK_GROUPS)

    def __post_init__(self) -> None:
        require_bounds(self)

    def select(self, ctx: SelectionContext, count: int = 1) -> Selection:
        run = self._diag if self.variant == "diag" else self._block
        return timed_selection(ctx, lambda order: run(ctx, order, count))

    def diag_gain(self, h: Tensor, fishers: Tensor) -> Tensor:
        """sum_i log1p(F_x,i / (H_i + lambda)): h [D], fishers [M, D] -> [M] (the higher the better)."""
        return torch.log1p(fishers / (h + self.lam)).sum(-1)

    def _diag(self, ctx, order, count):
        cands, h = pool_and_train_fishers(ctx, order, self.spec)
        return greedy_pick(cands, h, self.diag_gain, count, True)

    def _blocks(self, ctx, cameras):
        """Per view (seen [M], A [M, 9, P], G [M, 9, 9]) for the Gaussians the view reaches."""
        for f in view_factors(ctx.gaussians, cameras, ctx.background, self.block_spec, ctx.settings):
            yield f.seen, f.jacobian.dense().double(), f.feature_fisher

    def _taken_blocks(self, ctx) -> tuple[Tensor, Tensor]:
        """H_train per Gaussian [N, P, P] over the taken views, and the identity [P, P]."""
        n = len(ctx.gaussians)
        p = sum(v[0].numel() for k, v in ctx.gaussians.params().items() if k in self.block_spec.groups)
        eye = torch.eye(p, dtype=torch.float64)
        h = torch.zeros(n, p, p, dtype=torch.float64)
        for seen, A, G in self._blocks(ctx, ctx.taken):
            h[seen] += A.transpose(1, 2) @ G @ A
        return h, eye

    def _block_gains(self, ctx, sigma: Tensor, cameras: Cameras) -> Tensor:
        """sum_g log det(I + Sigma_g^1/2 F_x,g Sigma_g^1/2) of each camera [B], sigma [N, P, P]."""
        gains = torch.empty(len(cameras), dtype=torch.float64)
        for i, (seen, A, G) in enumerate(self._blocks(ctx, cameras)):
            m = A @ sigma[seen] @ A.transpose(1, 2)  # [M, 9, 9]; unseen Gaussians add log det I = 0
            gains[i] = torch.linalg.slogdet(torch.eye(9, dtype=torch.float64) + G @ m)[1].sum()
        return gains

    def _block(self, ctx, order, count):
        h, eye = self._taken_blocks(ctx)
        pool = ctx.candidates[order]
        picks, first = [], None
        for _ in range(min(count, len(order))):
            sigma = torch.linalg.inv(h + self.lam * eye)  # [N, P, P]
            scores = self._block_gains(ctx, sigma, pool)
            first = scores if first is None else first
            scores[picks] = -torch.inf
            best = int(torch.argmax(scores))
            picks.append(best)
            seen, A, G = next(self._blocks(ctx, pool[best]))
            h[seen] += A.transpose(1, 2) @ G @ A
        return picks, first

    def pose_scorer(self, ctx: SelectionContext) -> PoseScorer:
        """The information gain of any cameras, negated (a search minimises it); the posterior once."""
        if self.variant == "block":
            h, eye = self._taken_blocks(ctx)
            sigma = torch.linalg.inv(h + self.lam * eye)
            return PoseScorer(lambda cameras: -self._block_gains(ctx, sigma, cameras), maximizes=True)
        return gain_pose_scorer(ctx, self.spec, self.diag_gain)
