"""An episode's plan: everything about an episode that is fixed before its first step, made once.

``EpisodeOutline`` is what the config and the scene's format decide before the scene is read
(``plan=true`` prints it): the schedule (``pipeline.active.schedule``) and the fit recipe as run.
``EpisodePlan`` adds what the read scene decides: the protocol's views (``build_protocol``), the
curve's test views and 3DGS's scene extent. A job builds its plan once and hands the same object to
the episode, its ``result.json`` and the round messages; the viewer and the pre-flight check build
theirs the same way, so nothing re-derives a view id or a round count by its own rule.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from pipeline.active.config import EpisodeConfig, round_seed
from pipeline.active.schedule import Schedule, episode_schedule, scaled_fit
from pipeline.data.protocols import ProtocolViews, build_protocol, view_counts
from pipeline.data.sampling import sample_probes
from pipeline.data.scene import Scene, SceneTraits
from pipeline.fit.config import FitConfig
from pipeline.fit.trainer import scene_extent


def views_schedule(initial: int, budget: int, cfg: EpisodeConfig) -> Schedule:
    """The schedule rule applied to an episode of ``cfg`` with ``initial`` views and ``budget``."""
    return episode_schedule(initial, budget, cfg.views_per_round, cfg.epochs_per_view, cfg.fit.iterations,
                            reload=cfg.post_selection == "reload")


@dataclass(frozen=True)
class EpisodeOutline:
    """An episode's schedule and its fit recipe as run (rescaled to the schedule's horizon when the
    rounds outgrow the recipe; the very object ``cfg.fit`` when they do not)."""

    schedule: Schedule
    fit: FitConfig

    @property
    def evaluations(self) -> int:
        """The rounds that end in an evaluation: each selection round, then the final one."""
        return len(self.schedule.round_views) + 1

    @classmethod
    def before_reading(cls, traits: SceneTraits, cfg: EpisodeConfig) -> EpisodeOutline:
        """The outline of an episode of ``cfg`` on a scene of ``traits`` (its format's), before the
        scene is read: the protocol's view counts (``view_counts``, those ``build_protocol`` takes)
        through the schedule rule. ``EpisodePlan.of`` on the read scene gives the same outline."""
        schedule = views_schedule(*view_counts(traits, cfg.protocol), cfg)
        return cls(schedule, scaled_fit(cfg.fit, schedule))


@dataclass(frozen=True)
class EpisodePlan(EpisodeOutline):
    """The outline plus the read scene's part: the protocol's ``views``, ``curve_ids`` (the test
    views each round is evaluated on, an even subset of ``curve_test_views``) and ``extent`` (3DGS's
    scene extent from every camera the episode may train on: the initial views and the pool)."""

    views: ProtocolViews
    curve_ids: tuple[int, ...]
    extent: float

    @classmethod
    def of(cls, scene: Scene, cfg: EpisodeConfig) -> EpisodePlan:
        views = build_protocol(scene, cfg.protocol)
        schedule = views_schedule(len(views.initial_ids), views.budget, cfg)
        return cls(schedule, scaled_fit(cfg.fit, schedule), views,
                   tuple(uniform_subset(views.test_ids, cfg.curve_test_views)), episode_extent(scene, views))

    def probes(self, seed: int, round_index: int) -> list[int]:
        """The K probe ids of a round, drawn independently of the selection history (paper Sec. 5:
        a generator of its own, seeded by (seed, round)); benchmark definitions list them."""
        return probes_of_round(seed, round_index, self.views)

    def picks(self, round_index: int, views_per_round: int) -> int:
        """The picks round ``round_index`` asks for (the last round may ask for fewer)."""
        return int(min(views_per_round, self.views.budget - self.schedule.round_views[round_index]))


def uniform_subset(ids: list[int], count: int | None) -> list[int]:
    """``count`` ids spread evenly over ``ids`` (the first and the last among them); all of them
    when ``count`` is None or not smaller."""
    if count is None or count >= len(ids):
        return list(ids)
    return [ids[i] for i in np.linspace(0, len(ids) - 1, count).round().astype(int)]


def episode_extent(scene: Scene, views: ProtocolViews) -> float:
    """3DGS's scene extent for the whole episode: from every camera the episode may train on (the
    initial views and the candidate pool, all known before the first pick), as 3DGS and FisherRF
    take it from all training cameras; the same for every policy and every round."""
    ids = sorted(set(views.initial_ids) | set(views.pool_ids))
    return scene_extent(scene.split(views.pool_split).cameras[ids],
                        f"scene {scene.root} ({len(ids)} initial and pool cameras)")


def probes_of_round(seed: int, round_index: int, views: ProtocolViews) -> list[int]:
    """K probe ids for a round (``EpisodePlan.probes``)."""
    gen = torch.Generator().manual_seed(round_seed(seed, round_index))
    return sample_probes(views.probe_ids, views.probes, gen)
