"""Derivative-free search of a score over a pose space (lower is better, as GO-PRE's score).

The starts (e.g. the best pool candidates and random poses) are evaluated first; CMA-ES (the
``cma`` package) then refines from the best of them in the space's unit cube, bounded to it (the
azimuth of a full-circle shell wraps instead), until the budget of score evaluations or seconds is
spent. The result is the best pose evaluated, so it is never worse than the best start. Seeded:
the same seed, starts and score give the same poses.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch
from torch import Tensor

from pipeline.world.pose_space import LookAtShell

Score = Callable[[Tensor], Tensor]  # poses [B, 3] -> scores [B] (lower is better)


@dataclass(frozen=True)
class SearchBudget:
    evaluations: int = 120           # score evaluations in all, the starts included
    seconds: float | None = None     # wall-clock limit (None: evaluations only)
    population: int = 8              # CMA-ES population per generation
    sigma: float = 0.15              # initial step, in unit-cube coordinates

    def __post_init__(self) -> None:
        if self.evaluations < 1:
            raise ValueError(f"search budget evaluations must be >= 1, got {self.evaluations}")
        if self.seconds is not None and not self.seconds > 0:
            raise ValueError(f"search budget seconds must be > 0 or null, got {self.seconds}")
        if self.population < 2:
            raise ValueError(f"search population must be >= 2, got {self.population}")
        if not 0 < self.sigma <= 1:
            raise ValueError(f"search sigma must be in (0, 1], got {self.sigma}")


@dataclass
class SearchResult:
    pose: Tensor            # [3] the best (azimuth_deg, elevation_deg, radius)
    score: float
    poses: Tensor           # [E, 3] every evaluated pose, in order (the starts first)
    scores: Tensor          # [E]
    starts: int             # how many of them were starts
    seconds: float

    @property
    def evaluations(self) -> int:
        return len(self.scores)

    @property
    def best_start_score(self) -> float:
        return float(self.scores[:self.starts].min())


def search_poses(score: Score, space: LookAtShell, starts: Tensor, budget: SearchBudget,
                 seed: int) -> SearchResult:
    """Minimise ``score`` over ``space`` from ``starts`` [S, 3] (poses inside it) within ``budget``."""
    import cma

    if starts.ndim != 2 or starts.shape[1] != 3 or len(starts) == 0:
        raise ValueError(f"starts must be [S >= 1, 3] poses, got {tuple(starts.shape)}")
    if not bool(space.contains(starts).all()):
        raise ValueError("starts: every start must lie inside the pose space")
    clock = time.perf_counter()
    starts = starts[:budget.evaluations].double()
    poses, scores = [starts], [_scored(score, starts)]
    spent = len(starts)
    best = int(torch.argmin(scores[0]))
    x0 = space.unit_of_poses(starts[best:best + 1])[0].clamp(0, 1).tolist()
    wraps = space.azimuth_span_deg >= 360
    lower, upper = [None if wraps else 0.0, 0.0, 0.0], [None if wraps else 1.0, 1.0, 1.0]
    state = np.random.get_state()  # cma seeds NumPy's global generator: leave it as it was
    try:
        strategy = cma.CMAEvolutionStrategy(x0, budget.sigma, {
            "seed": seed + 1,  # cma reads 0 as "seed from the clock"
            "bounds": [lower, upper], "popsize": budget.population, "verbose": -9, "verb_log": 0,
            "verb_disp": 0, "tolfun": 0, "tolx": 1e-9})
        while spent < budget.evaluations and not _out_of_time(clock, budget):
            asked = strategy.ask(number=min(budget.population, budget.evaluations - spent))
            unit = torch.tensor(np.asarray(asked), dtype=torch.float64)
            batch = space.poses_of_unit(_into_cube(unit, wraps))
            values = _scored(score, batch)
            poses.append(batch)
            scores.append(values)
            spent += len(batch)
            if len(asked) == budget.population:  # CMA-ES updates on whole generations only
                strategy.tell(asked, values.tolist())
    finally:
        np.random.set_state(state)
    poses_all, scores_all = torch.cat(poses), torch.cat(scores)
    best = int(torch.argmin(scores_all))
    return SearchResult(poses_all[best], float(scores_all[best]), poses_all, scores_all, len(starts),
                        time.perf_counter() - clock)


def _into_cube(unit: Tensor, wraps: bool) -> Tensor:
    """The azimuth coordinate of a full-circle shell wraps (mod 1); the others stay in [0, 1]."""
    out = unit.clamp(0, 1)
    if wraps:
        out[:, 0] = torch.remainder(unit[:, 0], 1.0)
    return out


def _scored(score: Score, poses: Tensor) -> Tensor:
    values = torch.as_tensor(score(poses), dtype=torch.float64).reshape(-1)
    if len(values) != len(poses):
        raise ValueError(f"the score returned {len(values)} values for {len(poses)} poses")
    if not bool(torch.isfinite(values).all()):
        raise ValueError("the score returned a non-finite value")
    return values


def _out_of_time(clock: float, budget: SearchBudget) -> bool:
    return budget.seconds is not None and time.perf_counter() - clock >= budget.seconds
