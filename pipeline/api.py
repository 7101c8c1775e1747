"""gopre's public API: what a strategy from outside the package may rely on.

Everything here is a re-export; the names and their signatures are versioned by ``API_VERSION``
(``MAJOR.MINOR``: a minor version adds, a major one may change or remove) and a test fails when one
disappears or changes signature. A strategy is any class with ``select(self, ctx, count=1) ->
Selection`` (``Strategy``); options in the method YAML are its constructor's keyword arguments.
It reads the round through ``SelectionContext``:

- ``ctx.backend``: the current model's doors, ``render(cameras)``, ``view_fisher(cameras)``
  ([C, N, P] float64, the exact diag(J^T J)) and ``training_hessian(cameras)`` ([N, P]), on
  whichever backend the run uses (``ModelDoors``);
- ``ctx.candidates`` / ``ctx.candidate_ids`` (the pool), ``ctx.taken`` / ``ctx.taken_ids``
  (views trained on) and ``ctx.taken_images``, ``ctx.probes`` / ``ctx.probe_ids`` (the round's
  probe poses from the target manifold), ``ctx.goal_manifold`` (that manifold, None when the goal
  is the whole scene), ``ctx.gaussians`` (the model), ``ctx.generator`` (seeded per episode:
  draw randomness from it only, so a run is reproducible).

``timed_selection(ctx, run)`` builds the ``Selection`` record (timings, peak memory, every
candidate's score) from a function over the canonical pool order; a strategy that can score any
camera off the pool also offers ``pose_scorer(ctx) -> PoseScorer`` (the continuous search uses it).
Install a strategy as the entry point ``gopre.strategies`` (``name = package.module:Class``) or
name it as ``package.module:Class`` in a method YAML; see the README's "Your own method".
"""

from pipeline.acquisition import make_strategy, scores_any_pose
from pipeline.acquisition.base import (PoseScorer, Selection, SelectionContext, Strategy, canonical_order,
                                       greedy_pick, timed_selection)
from pipeline.acquisition.discovery import (ENTRY_POINT_GROUP, PluginIdentity, StrategyError,
                                            resolve_strategy)
from pipeline.acquisition.doors import ModelDoors
from pipeline.cameras import Cameras
from pipeline.fisher.exact import FisherSpec
from pipeline.splat import Gaussians, RenderSettings
from pipeline.splat.render import RenderOutput

API_VERSION = "1.1"  # 1.1: SelectionContext.on_fisher (progress of a Fisher pass)

__all__ = ["API_VERSION", "ENTRY_POINT_GROUP", "Cameras", "FisherSpec", "Gaussians", "ModelDoors",
           "PluginIdentity", "PoseScorer", "RenderOutput", "RenderSettings", "Selection", "SelectionContext",
           "Strategy", "StrategyError", "canonical_order", "greedy_pick", "make_strategy", "resolve_strategy",
           "scores_any_pose", "timed_selection"]
