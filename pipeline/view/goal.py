"""Score a goal drawn in the viewer with the sweeps' own GO-PRE strategy.

The goal is a target manifold: a sector (start angle, width, direction) or a list of picked pool
views. Probes are K pool views inside it (drawn with a seeded generator, as an episode draws
them); the candidates are the pool views not yet taken; the model, the taken views and the
strategy's options are the episode's at the chosen round (GO-PRE's defaults when the run used
another method).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from pipeline.acquisition import SelectionContext, make_strategy
from pipeline.data.manifolds import PoseListManifold, member_ids
from pipeline.data.protocols import resolved_manifold
from pipeline.data.sampling import sample_probes
from pipeline.view.run import EpisodeRun, RoundState


@dataclass
class GoalScores:
    manifold: dict               # the goal, in config form
    probes: list[int]            # the pool ids probed
    scores: dict[int, float]     # every remaining candidate's GO-PRE score (lower is better)
    best: int                    # the next best view


def pool_ids(run: EpisodeRun) -> list[int]:
    """Every view of the pool split the protocol lets an episode take (initial ones included)."""
    return sorted(set(run.views.pool_ids) | set(run.initial))


def goal_members(run: EpisodeRun, manifold: dict) -> list[int]:
    """Pool ids inside the goal manifold (a sector is resolved on the scene's cameras)."""
    ids = pool_ids(run)
    if manifold.get("kind") == "poses":
        wanted = PoseListManifold(list(manifold["view_ids"]))
        return [i for i in ids if i in set(wanted.view_ids)]
    up = torch.tensor(run.views.up, dtype=torch.float64)
    resolved = resolved_manifold(manifold, run.scene, up)
    return member_ids(resolved, run.pool.cameras[ids], ids)


def gopre_options(run: EpisodeRun) -> dict:
    return dict(run.job.options or {}) if run.job.strategy == "gopre" else {}


def score_goal(run: EpisodeRun, state: RoundState, manifold: dict, probes: int, seed: int = 0) -> GoalScores:
    """GO-PRE scores of the candidates left at ``state`` for the goal ``manifold`` with ``probes``
    probe poses inside it. ValueError when the goal holds no pool view or nothing is left."""
    inside = goal_members(run, manifold)
    if not inside:
        raise ValueError(f"the goal {manifold} holds no view of the pool to probe")
    taken = set(state.taken)
    remaining = [i for i in pool_ids(run) if i not in taken]
    if not remaining:
        raise ValueError("no candidate left: every pool view is taken")
    probe_ids = sample_probes(inside, probes, torch.Generator().manual_seed(seed))
    cams = run.pool.cameras
    background = run.scene.background.to(state.model.means)
    ctx = SelectionContext(state.model, cams[remaining], remaining, run.cameras_of(state.taken), background,
                           torch.Generator().manual_seed(seed), cams[probe_ids],
                           run.images_of(state.taken).to(state.model.means))
    selection = make_strategy("gopre", **gopre_options(run)).select(ctx, 1)
    return GoalScores(dict(manifold), probe_ids, dict(selection.scores), selection.chosen[0])
