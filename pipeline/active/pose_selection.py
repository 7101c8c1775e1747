"""Next-best-view beyond the pool: a pose searched in a pose space, its image captured
by a simulator, trained on like any view.

An episode with ``world != "dataset"`` still scores its pool each round (the records keep those
scores); the search then starts from the poses of the ``pool_starts`` best pool candidates (those
inside the pose space) and ``random_starts`` random poses, minimises the strategy's own score of a
camera (``pose_scorer``) with CMA-ES (``pipeline.world.search``), and the best pose found is
captured. Acquired views get the ids after the pool's: view ``first_id + a`` is the a-th one.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field

import torch
from torch import Tensor

from pipeline.acquisition import SelectionContext
from pipeline.acquisition.base import PoseScorer
from pipeline.active.config import EpisodeConfig, round_seed
from pipeline.cameras import Cameras
from pipeline.data.manifolds import SectorManifold
from pipeline.data.protocols import ProtocolConfig, ProtocolViews, resolved_manifold, scene_up
from pipeline.data.scene import Scene
from pipeline.splat import ply
from pipeline.world import GeneratedWorld, LookAtShell, SearchBudget, TwinWorld, World, search_poses


@dataclass
class AcquiredViews:
    """The views captured off the pool, in order; their ids start at ``first_id`` (the pool's size)."""

    first_id: int
    poses: list[list[float]] = field(default_factory=list)   # (azimuth_deg, elevation_deg, radius)
    cameras: Cameras | None = None
    images: Tensor | None = None                              # [A, H, W, 3]

    def add(self, pose: list[float], camera: Cameras, image: Tensor) -> int:
        self.poses.append([float(x) for x in pose])
        self.cameras = camera if self.cameras is None else Cameras.cat([self.cameras, camera])
        self.images = image if self.images is None else torch.cat([self.images, image])
        return self.first_id + len(self.poses) - 1

    def is_acquired(self, view: int) -> bool:
        return view >= self.first_id

    def camera(self, view: int) -> Cameras:
        return self.cameras[[view - self.first_id]]

    def image(self, view: int) -> Tensor:
        return self.images[view - self.first_id]

    def state(self) -> dict:
        if self.cameras is None:
            return {"poses": []}
        return {"poses": self.poses, "viewmats": self.cameras.viewmats, "Ks": self.cameras.Ks,
                "width": self.cameras.width, "height": self.cameras.height, "images": self.images}

    def restore(self, state: dict) -> None:
        self.poses = [list(p) for p in state["poses"]]
        if self.poses:
            self.cameras = Cameras(state["viewmats"], state["Ks"], state["width"], state["height"])
            self.images = state["images"]
        else:
            self.cameras, self.images = None, None


def make_world(scene: Scene, cfg: EpisodeConfig) -> World:
    """The episode's capture simulator (``cfg.world``)."""
    if cfg.world == "generated":
        info = scene.root / "scene.json"
        if not info.exists():
            raise ValueError(f"world=generated needs a generated scene: no {info}")
        return GeneratedWorld(int(json.loads(info.read_text())["size"]), scene.background)
    if cfg.world == "twin":
        return TwinWorld(ply.load(cfg.world_model[len("ply:"):]), scene.background)
    raise ValueError(f"no capture simulator for world={cfg.world!r}")


def episode_pose_space(scene: Scene, views: ProtocolViews, protocol: ProtocolConfig) -> LookAtShell:
    """The shell the episode's initial and pool cameras span (all azimuths for an object scene),
    about the scene box's centre (moved
    in the plane to the sector's centre for a sector goal), up from the sector manifold or estimated from the
    cameras; restricted to the target sector for a sector goal (the goal protocol's manifold)."""
    manifold = (resolved_manifold(protocol.manifold, scene, scene_up(scene, scene.all_cameras(), protocol.up))
                if protocol.kind == "goal" else None)
    cams = scene.split(views.pool_split).cameras[sorted(set(views.initial_ids) | set(views.pool_ids))]
    lo, hi = scene.bounds()
    centre = ((lo + hi) / 2).double()
    radius = float(((hi - lo) / 2).double().norm())
    if isinstance(manifold, SectorManifold) and manifold.up is not None:
        up = torch.tensor(manifold.up, dtype=torch.float64)
        up = up / up.norm()
        # the sector measures azimuths about its centre (the cameras' centroid): the shell keeps the
        # box centre's height and takes the sector centre's place in the plane
        offset = torch.tensor(manifold.center, dtype=torch.float64) - centre
        centre = centre + offset - (offset @ up) * up
    else:  # the protocols' up: z for an object scene, estimated from every camera of a real one
        up = scene_up(scene, scene.all_cameras(), protocol.up)
    # an object scene's bounding radius must stay outside every pose; a real capture's cameras
    # stand inside its point cloud's box, so there the bound does not apply
    obj = scene.traits.kind == "object"  # an object scene: the whole shell around it
    space = LookAtShell.spanning(cams, centre, up / up.norm(), scene_radius=radius if obj else 0.0,
                                 full_circle=True if obj else None)
    if isinstance(manifold, SectorManifold):
        space = space.within_sector(manifold)
    return space


@dataclass
class PoseChoice:
    pose: list[float]          # (azimuth_deg, elevation_deg, radius)
    camera: Cameras            # [1]
    score: float
    best_start_score: float
    evaluations: int
    seconds: float
    evaluated: list[list[float]]  # every evaluated (azimuth_deg, elevation_deg, radius, score), in order


def search_next_pose(scorer: PoseScorer, ctx: SelectionContext, pool_costs: dict[int, float],
                     space: LookAtShell, cfg: EpisodeConfig, round_index: int) -> PoseChoice:
    """The pose of least cost (``scorer``): starts from the poses of the pool candidates of least
    cost and random poses, then CMA-ES; seeded by (episode seed, round)."""
    options = cfg.search_options()
    seed = round_seed(cfg.seed, round_index)
    best_ids = sorted(pool_costs, key=lambda i: (pool_costs[i], i))[:options["pool_starts"]]
    position = {view: k for k, view in enumerate(ctx.candidate_ids)}
    starts = []
    if best_ids:
        pool_poses = space.poses_of(ctx.candidates[[position[i] for i in best_ids]])
        starts.append(pool_poses[space.contains(pool_poses)])
    starts.append(space.sample(options["random_starts"], torch.Generator().manual_seed(seed)))
    starts = torch.cat(starts)
    if len(starts) == 0:
        starts = space.sample(1, torch.Generator().manual_seed(seed))
    budget = SearchBudget(evaluations=max(options["evaluations"], len(starts)), seconds=options["seconds"])
    result = search_poses(lambda poses: scorer.cost(space.cameras(poses)), space, starts, budget, seed)
    evaluated = torch.cat([result.poses, result.scores[:, None]], 1).tolist()
    return PoseChoice(result.pose.tolist(), space.cameras(result.pose[None]), result.score,
                      result.best_start_score, result.evaluations, round(result.seconds, 3), evaluated)
