"""The acquisition protocol: a strategy picks views from a candidate pool given the current model.

Every strategy returns a ``Selection`` with its instrumentation (seconds per candidate, seconds
per round, peak memory) and the score of every candidate at the first pick.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable, Protocol

import torch
from torch import Tensor

from pipeline.acquisition.doors import ModelDoors
from pipeline.cameras import Cameras
from pipeline.fisher.exact import FisherSpec, SparseFisher, view_fisher, view_fisher_sparse
from pipeline.memory import peak_rss_mb
from pipeline.splat import Gaussians, RenderSettings


@dataclass
class SelectionContext:
    """What a strategy may look at. Pool entries are identified by dataset view ids."""

    gaussians: Gaussians
    candidates: Cameras              # [M] the pool
    candidate_ids: list[int]         # [M] dataset ids of the pool entries
    taken: Cameras                   # views already trained on
    background: Tensor               # [3]
    generator: torch.Generator
    probes: Cameras | None = None    # K probe poses from the target manifold (goal strategies)
    taken_images: Tensor | None = None  # [C_taken, H, W, 3] (strategies that use errors)
    settings: RenderSettings = field(default_factory=RenderSettings)
    # the pool ids of the taken views and of the probes, when they are pool views (the episode's
    # are): a probe that is a candidate or a taken view reuses that view's Fisher (same model)
    taken_ids: list[int] | None = None
    probe_ids: list[int] | None = None
    # the target manifold the probes come from, as the protocol declares it (e.g. {"kind":
    # "sector", "start_deg": 0, "width_deg": 120, "clockwise": True, "up": [x, y, z]}); None
    # when the whole scene is the goal (the global and sparse protocols)
    goal_manifold: dict | None = None
    # hears (views whose Fisher is computed, of the views asked) as a Fisher pass goes, a chunk of
    # ``FISHER_CHUNK`` views at a time (progress a user can follow inside a long selection)
    on_fisher: Callable[[int, int], None] | None = None
    fisher_seconds: float = field(default=0.0, init=False)  # time spent in Fisher passes
    fisher_views: int = field(default=0, init=False)

    def __post_init__(self) -> None:
        if len(self.candidates) != len(self.candidate_ids):
            raise ValueError(f"candidate_ids has {len(self.candidate_ids)} entries for "
                             f"{len(self.candidates)} candidate cameras")
        if len(self.candidate_ids) == 0:
            raise ValueError("candidates: the pool is empty")
        for name, ids, cams in (("taken_ids", self.taken_ids, self.taken),
                                ("probe_ids", self.probe_ids, self.probes)):
            if ids is not None and (cams is None or len(ids) != len(cams)):
                raise ValueError(f"{name} has {len(ids)} entries for "
                                 f"{0 if cams is None else len(cams)} cameras")

    @property
    def backend(self) -> ModelDoors:
        """The current model's doors (render, per-view Fisher, training Hessian), the backend
        resolved once for the model's device: what a strategy from outside should call."""
        return ModelDoors.of(self.gaussians, self.background, self.settings)


@dataclass
class Selection:
    chosen: list[int]                 # dataset ids, in pick order
    scores: dict[int, float]          # every candidate's score at the first pick
    seconds_per_candidate: float
    round_seconds: float
    peak_rss_mb: float
    fisher_seconds: float = 0.0       # of round_seconds, spent computing Fisher (all views)
    fisher_views: int = 0             # candidates + taken + probes whose Fisher was computed


class Strategy(Protocol):
    name: str

    def select(self, ctx: SelectionContext, count: int = 1) -> Selection: ...


@dataclass(frozen=True)
class PoseScorer:
    """A strategy's score of any camera, as the cost a search over poses minimises.

    ``cost(cameras [B]) -> [B]`` float64, lower is better, equal to the score ``select`` gives the
    same camera as a candidate on the same context (its first pick), negated for a strategy that
    picks the highest score (``maximizes``). Strategies that can score a pose off the pool have
    ``pose_scorer(ctx) -> PoseScorer``."""

    cost: Callable[[Cameras], Tensor]
    maximizes: bool

    def pool_costs(self, scores: dict[int, float]) -> dict[int, float]:
        """``Selection.scores`` (the strategy's own sign) as costs."""
        return {view: -s if self.maximizes else s for view, s in scores.items()}


def gain_pose_scorer(ctx: SelectionContext, spec: FisherSpec,
                     gain: Callable[[Tensor, Tensor], Tensor]) -> PoseScorer:
    """The pose scorer of a strategy that maximises ``gain(h [D], fishers [B, D]) -> [B]`` over
    the diagonal Fisher: cost = -gain, H_train (the taken views' summed Fisher) computed once."""
    h = taken_fisher(ctx, spec)

    def cost(cameras: Cameras) -> Tensor:
        fishers = fisher_vectors(ctx, cameras, spec)  # [B, D]
        return -gain(h if h is not None else torch.zeros_like(fishers[0]), fishers)
    return PoseScorer(cost, maximizes=True)


FISHER_CHUNK = 16  # views per Fisher call when someone listens (each view's numbers do not depend on it)


def in_chunks(ctx: SelectionContext, cameras: Cameras, compute: Callable[[Cameras], object]) -> list:
    """``[compute(cameras)]``, timed and counted into ``ctx``; with ``ctx.on_fisher`` set, the
    outputs of ``FISHER_CHUNK`` views at a time, reporting (done, total) after each chunk."""
    start = time.perf_counter()
    if ctx.on_fisher is None:
        out = [compute(cameras)]
    else:
        out = []
        for first in range(0, len(cameras), FISHER_CHUNK):
            last = min(first + FISHER_CHUNK, len(cameras))
            out.append(compute(cameras[list(range(first, last))]))
            ctx.on_fisher(last, len(cameras))
    ctx.fisher_seconds += time.perf_counter() - start
    ctx.fisher_views += len(cameras)
    return out


def fisher_vectors(ctx: SelectionContext, cameras: Cameras, spec: FisherSpec) -> Tensor:
    """Flattened exact diagonal Fisher of each view, [C, D] float64 (C >= 1: callers never ask for
    the Fisher of no view)."""
    chunks = in_chunks(ctx, cameras, lambda cams: view_fisher(ctx.gaussians, cams, ctx.background, spec,
                                                              ctx.settings).flatten(1))
    return chunks[0] if len(chunks) == 1 else torch.cat(chunks)


def sparse_fishers(ctx: SelectionContext, cameras: Cameras, spec: FisherSpec) -> list[SparseFisher]:
    """``fisher_vectors`` as one compact ``SparseFisher`` per view (timed and counted the same)."""
    chunks = in_chunks(ctx, cameras, lambda cams: view_fisher_sparse(ctx.gaussians, cams, ctx.background, spec,
                                                                     ctx.settings))
    return [view for chunk in chunks for view in chunk]


def sparse_fishers_reusing(ctx: SelectionContext, cameras: Cameras, ids: list[int] | None,
                           known: dict[int, SparseFisher], spec: FisherSpec) -> list[SparseFisher]:
    """``sparse_fishers`` of ``cameras`` (pool ids ``ids``), taking a view's Fisher from ``known``
    (pool id -> Fisher of this round's model) instead of recomputing it; order kept."""
    if ids is None:
        return sparse_fishers(ctx, cameras, spec)
    missing = [k for k, i in enumerate(ids) if i not in known]
    computed = dict(zip(missing, sparse_fishers(ctx, cameras[missing], spec))) if missing else {}
    return [computed[k] if k in computed else known[i] for k, i in enumerate(ids)]


def summed_fisher(views: list[SparseFisher], n: int, width: int) -> Tensor:
    """The sum of the views' Fishers, [N, P] float64 (zeros for no view)."""
    total = torch.zeros(n, width, dtype=torch.float64)
    for view in views:
        total.index_add_(0, view.ids, view.rows)
    return total


def greedy_pick_sparse(candidates: list[SparseFisher], h_train: Tensor,
                       scores_given: Callable[[Tensor, list[SparseFisher]], Tensor],
                       count: int) -> tuple[list[int], Tensor]:
    """``greedy_pick`` (argmin) over compact candidate Fishers: h_train [N, P];
    scores_given(h, candidates) -> [M]; the conditional update H <- H + F_pick on the pick's rows.
    Ties go to the lowest position, as ``greedy_pick``."""
    available = torch.ones(len(candidates), dtype=torch.bool)
    h = h_train.clone()
    picks, first = [], None
    for _ in range(min(count, len(candidates))):
        s = scores_given(h, candidates)
        first = s if first is None else first
        best = int(torch.argmin(torch.where(available, s, torch.full_like(s, torch.inf))))
        picks.append(best)
        available[best] = False
        h.index_add_(0, candidates[best].ids, candidates[best].rows)
    return picks, first


def taken_fisher(ctx: SelectionContext, spec: FisherSpec) -> Tensor | None:
    """H_train [D]: the taken views' summed Fisher with the current model (None when nothing is
    taken yet: its size then comes from the first Fisher computed)."""
    return fisher_vectors(ctx, ctx.taken, spec).sum(0) if len(ctx.taken) else None


def pool_and_train_fishers(ctx: SelectionContext, order: list[int],
                           spec: FisherSpec) -> tuple[Tensor, Tensor]:
    """Fisher of the candidates in ``order`` [M, D] and H_train [D] (the sum over the taken views,
    recomputed with the current model; zeros when nothing is taken yet)."""
    cands = fisher_vectors(ctx, ctx.candidates[order], spec)
    h = taken_fisher(ctx, spec)
    return cands, h if h is not None else torch.zeros_like(cands[0])


def greedy_pick(candidate_fishers: Tensor, h_train: Tensor, score: Callable[[Tensor, Tensor], Tensor],
                count: int, maximize: bool) -> tuple[list[int], Tensor]:
    """Greedy batch selection with the conditional update H <- H + F_pick between picks.

    candidate_fishers [M, D]; h_train [D]; score(h_train, fishers [M, D]) -> [M].
    Returns pool indices in pick order and the first pick's scores [M]. Ties go to the lowest
    dataset order (stable), so the result does not depend on the order of the pool.
    """
    available = torch.ones(candidate_fishers.shape[0], dtype=torch.bool)
    h = h_train.clone()
    picks, first = [], None
    for _ in range(min(count, candidate_fishers.shape[0])):
        s = score_in_blocks(score, h, candidate_fishers)
        first = s if first is None else first
        masked = torch.where(available, s, torch.full_like(s, -torch.inf if maximize else torch.inf))
        best = int(torch.argmax(masked) if maximize else torch.argmin(masked))
        picks.append(best)
        available[best] = False
        h = h + candidate_fishers[best]
    return picks, first


SCORE_BLOCK_ELEMENTS = 1 << 22  # candidate rows scored together: ~32 MB of float64 temporaries


def score_in_blocks(score: Callable[[Tensor, Tensor], Tensor], h: Tensor, fishers: Tensor) -> Tensor:
    """score(h, fishers) [M] computed a block of candidate rows at a time, so the [M, D] float64
    temporaries of a score never exist at once (scores are row-wise independent)."""
    rows = max(1, SCORE_BLOCK_ELEMENTS // max(1, fishers.shape[-1]))
    return torch.cat([score(h, fishers[i:i + rows]) for i in range(0, fishers.shape[0], rows)])


def canonical_order(ctx: SelectionContext) -> list[int]:
    """Pool indices sorted by dataset id: strategies work in this order (order invariance)."""
    return sorted(range(len(ctx.candidate_ids)), key=lambda i: ctx.candidate_ids[i])


def timed_selection(ctx: SelectionContext, run: Callable[[list[int]], tuple[list[int], Tensor]],
                    ) -> Selection:
    """Run ``run(order)`` -> (picked positions in ``order``, scores aligned with ``order``)."""
    start = time.perf_counter()
    ctx.fisher_seconds, ctx.fisher_views = 0.0, 0
    order = canonical_order(ctx)
    picked, scores = run(order)
    seconds = time.perf_counter() - start
    ids = [ctx.candidate_ids[order[p]] for p in picked]
    return Selection(ids, {ctx.candidate_ids[i]: float(s) for i, s in zip(order, scores)},
                     seconds / len(order), seconds, peak_rss_mb(), ctx.fisher_seconds,
                     ctx.fisher_views)
