"""Evaluation protocols of the paper: which views are the candidate pool, the test set, the
initial views, the probe pool and the budget (the schedule is part of the episode config).

- ``global``: Blender: the official train split is the pool, the full test split is the test set;
  COLMAP scenes: the LLFF hold-out (every 8th image in name order) is the test set, the rest the pool.
- ``goal``: a target manifold (default: the 120-degree clockwise sector). Blender: test views
  restricted to the manifold, the whole train split as pool; COLMAP: the LLFF hold-out applied to
  the views inside the manifold gives the test set, all remaining views form the pool. Probes are
  drawn from the pool views inside the manifold.
- ``sparse``: the global split with a 10-view budget (2 initial views, +1 per round).
Initial views are spread uniformly in azimuth around the up axis (2 for Blender, 4 for real scenes).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from pipeline.bounds import FLOAT, INT, STR, bounded, require_bounds
from pipeline.cameras import Cameras
from pipeline.data.manifolds import SectorManifold, azimuths_deg, estimate_up, manifold_from_dict, member_ids
from pipeline.data.orientation import orientation, parse_up
from pipeline.data.sampling import probe_count
from pipeline.data.scene import Scene, SceneTraits

KINDS = ("global", "goal", "sparse")


@dataclass
class ProtocolConfig:
    kind: str = bounded("global", STR, choices=KINDS)
    initial_views: int | None = bounded(None, INT, ge=1, nullable=True)  # None: 2 for Blender, 4 for real scenes
    budget: int | None = bounded(None, INT, ge=2, nullable=True)  # total views; None: 10 for Blender/sparse,
    # 20 otherwise
    probes: int | float | None = bounded(None, FLOAT, gt=0, nullable=True)  # K, or a fraction of all N
    # views of the pool split (paper Table 5: N/4 ... N/64); None: 25 / 1/8
    manifold: dict = field(default_factory=lambda: {"kind": "sector", "start_deg": 0.0,
                                                     "width_deg": 120.0, "clockwise": True})
    llff_hold: int = bounded(8, INT, ge=2)
    probe_manifold: dict | None = None    # draw probes from this manifold only (the paper's
                                          # goal-metric misalignment ablation under ``global``)
    # the scene's up axis (``pipeline.data.orientation``): cameras | plane | pca | [x, y, z]; None: the
    # scene's own (a capture's --up kept in capture.json, else +z for the Blender layout, else cameras);
    # set by a dataset entry's ``up``
    up: str | list | None = None

    def __post_init__(self) -> None:
        require_bounds(self)
        self.up = parse_up(self.up)
        k = self.probes  # a count (a whole number) or a fraction below 1
        if isinstance(k, float) and k > 1 and not k.is_integer():
            raise ValueError(f"probes: {k!r} is not a count >= 1 or a fraction in (0, 1)")
        if self.initial_views is not None and self.budget is not None and self.initial_views >= self.budget:
            raise ValueError(f"initial_views: {self.initial_views} leaves no pick within budget={self.budget}")


@dataclass
class ProtocolViews:
    """View ids index ``pool_split`` / ``test_split`` of the scene."""

    pool_split: str
    pool_ids: list[int]          # candidates (initial views excluded)
    initial_ids: list[int]
    test_split: str
    test_ids: list[int]
    probe_ids: list[int]         # pool views the probes are drawn from
    budget: int
    probes: int                  # K, resolved: a fraction counts all views of the pool split
    up: list[float]

    @property
    def rounds(self) -> int:
        return self.budget - len(self.initial_ids)


def scene_up(scene: Scene, cameras: Cameras, choice: str | list | None = None) -> torch.Tensor:
    """The up axis [3]: ``choice`` (a dataset entry's ``up``), else the scene's own (``info["up"]``,
    a capture's ``--up``), else +z for a scene whose traits say so (the Blender layout), else
    estimated from the cameras (``pipeline.data.orientation``)."""
    choice = choice if choice is not None else scene.info.get("up")
    if choice is None:
        return torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64) if scene.traits.up == "z" else estimate_up(cameras)
    return torch.tensor(orientation(cameras, scene.points, choice).up, dtype=torch.float64)


def uniform_initial(cameras: Cameras, ids: list[int], count: int, up: torch.Tensor) -> list[int]:
    """``count`` ids spread evenly in azimuth (nearest unused view to each target angle)."""
    if count > len(ids):
        raise ValueError(f"initial_views={count} exceeds the pool of {len(ids)} views")
    az = azimuths_deg(cameras, up, cameras.centers.double().mean(0))
    chosen: list[int] = []
    for k in range(count):
        target = k * 360.0 / count
        gap = ((az - target + 180) % 360 - 180).abs()
        for i in torch.argsort(gap, stable=True).tolist():
            if ids[i] not in chosen:
                chosen.append(ids[i])
                break
    return chosen


def resolved_manifold(data: dict, scene: Scene, up: torch.Tensor):
    """A manifold from its dict, a sector's up axis defaulting to the scene's, resolved on the
    scene's cameras."""
    manifold = manifold_from_dict(data)
    if isinstance(manifold, SectorManifold) and manifold.up is None:
        manifold.up = up.tolist()
    return manifold.resolve(scene.all_cameras())


def view_counts(traits: SceneTraits, cfg: ProtocolConfig) -> tuple[int, int]:
    """(initial views, budget) of ``cfg`` on a scene with ``traits``: the config's, else the
    paper's defaults (Blender layout or sparse: 2 -> 10; a real scene: 4 -> 20)."""
    real_default = traits.split != "given" and cfg.kind != "sparse"
    initial = cfg.initial_views if cfg.initial_views is not None else (4 if real_default else 2)
    budget = cfg.budget if cfg.budget is not None else (20 if real_default else 10)
    return initial, budget


def build_protocol(scene: Scene, cfg: ProtocolConfig) -> ProtocolViews:
    blender = scene.traits.split == "given"  # the files' train / test splits (the Blender layout)
    initial, budget = view_counts(scene.traits, cfg)
    probes = cfg.probes if cfg.probes is not None else (25 if blender else 0.125)
    if blender:
        pool_split, test_split = "train", "test"
        pool_all = list(range(len(scene.split("train"))))
        test_all = list(range(len(scene.split("test"))))
    else:
        pool_split = test_split = "all"
        n = len(scene.split("all"))
        test_all = [i for i in range(n) if i % cfg.llff_hold == 0]
        pool_all = [i for i in range(n) if i % cfg.llff_hold != 0]
    pool_cams = scene.split(pool_split).cameras
    up = scene_up(scene, scene.all_cameras(), cfg.up)
    probe_pool = pool_all
    if cfg.kind == "goal":
        manifold = resolved_manifold(cfg.manifold, scene, up)
        if blender:
            test_cams = scene.split("test").cameras
            test_all = member_ids(manifold, test_cams[test_all], test_all)
            probe_pool = member_ids(manifold, pool_cams[pool_all], pool_all)
        else:
            inside = member_ids(manifold, pool_cams, list(range(len(pool_cams))))
            test_all = inside[::cfg.llff_hold]
            held = set(test_all)
            pool_all = [i for i in range(len(pool_cams)) if i not in held]
            probe_pool = [i for i in inside if i not in held]
        if not test_all:
            raise ValueError(f"protocol 'goal': the target manifold {cfg.manifold} holds no test view")
        if not probe_pool:
            raise ValueError(f"protocol 'goal': the target manifold {cfg.manifold} holds no pool view to probe")
    if cfg.probe_manifold is not None:
        probe_manifold = resolved_manifold(cfg.probe_manifold, scene, up)
        probe_pool = member_ids(probe_manifold, pool_cams[probe_pool], probe_pool)
        if not probe_pool:
            raise ValueError(f"protocol: probe_manifold {cfg.probe_manifold} holds no pool view")
    if not test_all:
        raise ValueError(f"protocol {cfg.kind!r}: the test set is empty")
    init = uniform_initial(pool_cams[pool_all], pool_all, initial, up)
    if budget <= initial:
        raise ValueError(f"budget={budget} must exceed initial_views={initial}")
    pool = [i for i in pool_all if i not in set(init)]
    if budget > initial + len(pool):
        raise ValueError(f"budget={budget} exceeds the {initial} initial views plus the {len(pool)} "
                         f"views the pool can still give")
    # the paper draws probes from all training views in the target manifold, the initial views
    # included (until the fidelity fixes they were removed from the probe pool)
    probe_ids = list(probe_pool)
    k = min(probe_count(probes, len(pool_cams)), len(probe_ids))
    return ProtocolViews(pool_split, pool, init, test_split, test_all, probe_ids, budget, k, up.tolist())
