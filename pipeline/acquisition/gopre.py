"""``gopre``: argmin over the pool of sum_i log1p(Sx_i M_i / tau^2) (paper Eq. final-objective).

M is the goal Hessian, the mean Fisher of K probe poses from the target manifold. Ablations:
``goal="identity"`` (M = I, w/o goal Hessian), ``tau=0`` (w/o observation noise: the exact
tau -> 0 limit of the score, where M's values drop out of the ranking; ``fisher.posterior`` derives
it; tau enters the score only, the posterior is the paper's unit-noise one),
``score="trace"`` (trace approximation), ``score="mc"`` (direct Monte-Carlo over the probes),
``fisher_groups="without_sh_rest"`` (the Fisher without the higher-order SH coefficients).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor

from pipeline.bounds import FLOAT, STR, bounded, require_bounds
from pipeline.acquisition.base import (PoseScorer, Selection, SelectionContext, fisher_vectors, greedy_pick,
                                       greedy_pick_sparse, pool_and_train_fishers, sparse_fishers,
                                       sparse_fishers_reusing, summed_fisher, taken_fisher,
                                       timed_selection)
from pipeline.cameras import Cameras
from pipeline.fisher.exact import FisherSpec, fused_fisher_available
from pipeline.fisher.features import PARAM_GROUPS
from pipeline.fisher.posterior import (POSTERIOR_LAMBDA, goal_hessian, gopre_limit_score,
                                       gopre_score_of_fishers, gopre_scores_sparse,
                                       monte_carlo_score, posterior_variance, trace_score,
                                       updated_variance)

SCORES = ("logdet", "trace", "mc")
GOALS = ("probes", "identity")
# the Fisher's parameter groups (ablation): every raw parameter, or without the SH rest (degree >= 1)
FISHER_GROUPS = {"all": PARAM_GROUPS, "without_sh_rest": tuple(g for g in PARAM_GROUPS if g != "shN")}


@dataclass
class GoPreStrategy:
    name: str = "gopre"
    lam: float = bounded(POSTERIOR_LAMBDA, FLOAT, gt=0)
    tau: float = bounded(1.0, FLOAT, ge=0)                       # 0: the tau -> 0 limit
    goal: str = bounded("probes", STR, choices=GOALS)
    score: str = bounded("logdet", STR, choices=SCORES)
    fisher_groups: str = bounded("all", STR, choices=tuple(FISHER_GROUPS))
    spec: FisherSpec = field(init=False)

    def __post_init__(self) -> None:
        require_bounds(self)
        self.spec = FisherSpec(groups=FISHER_GROUPS[self.fisher_groups])
        if self.tau == 0 and self.score != "logdet":
            raise ValueError(f"gopre tau = 0 (the limit) is defined for score='logdet' only, "
                             f"got score={self.score!r}")

    def _scorer(self, probes: torch.Tensor | None):
        tau = self.tau
        if self.score == "mc":
            return lambda h, f: monte_carlo_score(
                updated_variance(posterior_variance(h, self.lam), f), probes, tau)
        goal = goal_hessian(probes) if probes is not None else None

        def score(h, f):
            s = posterior_variance(h, self.lam)
            m = torch.ones_like(s) if goal is None else goal
            if tau > 0 and self.score == "logdet":
                return gopre_score_of_fishers(s, f, m, tau)
            sx = updated_variance(s, f)
            if tau == 0:
                return gopre_limit_score(sx, m)
            return trace_score(sx, m, tau)
        return score

    def _sparse_run(self, ctx: SelectionContext, count: int):
        """The logdet score (tau > 0) over compact candidate Fishers: the same picks and scores
        as the dense path without its [M, N, P] block (used when the fused compiled Fisher is).
        A probe that is a candidate or a taken view (the global protocol draws probes from every
        training view) reuses that view's Fisher: the same model, the same numbers."""
        def run(order):
            cands = sparse_fishers(ctx, ctx.candidates[order], self.spec)
            n = len(ctx.gaussians)
            width = cands[0].rows.shape[1]
            taken = sparse_fishers(ctx, ctx.taken, self.spec) if len(ctx.taken) else []
            h = summed_fisher(taken, n, width)
            if self.goal == "probes":
                known = {ctx.candidate_ids[i]: f for i, f in zip(order, cands)}
                if ctx.taken_ids is not None:
                    known.update(zip(ctx.taken_ids, taken))
                probes = sparse_fishers_reusing(ctx, ctx.probes, ctx.probe_ids, known, self.spec)
                goal = summed_fisher(probes, n, width)
                goal /= len(ctx.probes)  # M = mean over the K probes
            else:
                goal = torch.ones(n, width, dtype=torch.float64)

            def scores(h_now, views):
                return gopre_scores_sparse(posterior_variance(h_now, self.lam), goal, views, self.tau)
            return greedy_pick_sparse(cands, h, scores, count)
        return run

    def pose_scorer(self, ctx: SelectionContext) -> PoseScorer:
        """The score ``select`` gives a candidate, for any cameras (lower is better) on ctx's model,
        taken views and probes: what a search over the pose space minimises. The posterior and the
        goal Hessian are computed once; each call computes its cameras' Fishers."""
        if self.goal == "probes" and (ctx.probes is None or len(ctx.probes) == 0):
            raise ValueError("gopre needs probe poses from the target manifold (ctx.probes)")
        h = taken_fisher(ctx, self.spec)
        score = self._scorer(fisher_vectors(ctx, ctx.probes, self.spec) if self.goal == "probes" else None)

        def cost(cameras: Cameras) -> Tensor:
            fishers = fisher_vectors(ctx, cameras, self.spec)  # [B, D]
            return score(h if h is not None else torch.zeros_like(fishers[0]), fishers)
        return PoseScorer(cost, maximizes=False)

    def select(self, ctx: SelectionContext, count: int = 1) -> Selection:
        if self.goal == "probes" and (ctx.probes is None or len(ctx.probes) == 0):
            raise ValueError("gopre needs probe poses from the target manifold (ctx.probes)")
        if self.score == "logdet" and self.tau > 0 and fused_fisher_available(ctx.gaussians,
                                                                             ctx.settings):
            return timed_selection(ctx, self._sparse_run(ctx, count))

        def run(order):
            cands, h = pool_and_train_fishers(ctx, order, self.spec)
            probes = fisher_vectors(ctx, ctx.probes, self.spec) if self.goal == "probes" else None
            return greedy_pick(cands, h, self._scorer(probes), count, maximize=False)
        return timed_selection(ctx, run)
