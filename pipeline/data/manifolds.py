"""Target view manifolds: the user's goal, as a first-class object serialisable to config.

- ``SectorManifold``: a sector of the circle of views around the centroid of the camera positions,
  in the plane orthogonal to the scene's up axis; ``start_deg`` and ``width_deg`` (the paper: 120
  degrees), measured clockwise when looking down the up axis, from the in-plane direction of the
  world axis ``reference`` (x by default, y if x is nearly parallel to up).
- ``PoseListManifold``: an explicit list of views (by dataset id).
- ``RegionManifold``: the views that see a 3D region of interest (a ball) inside their image.
Every manifold answers ``contains(cameras) -> [C] bool`` and converts to and from a dict.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import torch
from torch import Tensor

from pipeline.cameras import Cameras


def estimate_up(cameras: Cameras) -> Tensor:
    """World up [3] from cameras: the mean of their -y axes (OpenCV y points down), normalised.

    Captures are taken upright, so the cameras' up directions agree; works for COLMAP scenes
    whose world frame is arbitrary.
    """
    up = -cameras.viewmats[:, 1, :3].double().mean(0)
    if up.norm() < 1e-6:
        raise ValueError("cannot estimate the up axis: camera up vectors cancel out")
    return up / up.norm()


def plane_basis(up: Tensor, reference: int) -> tuple[Tensor, Tensor]:
    axis = torch.zeros(3, dtype=torch.float64)
    axis[reference] = 1
    if abs(float(axis @ up)) > 0.95:
        axis = torch.zeros(3, dtype=torch.float64)
        axis[(reference + 1) % 3] = 1
    e1 = axis - (axis @ up) * up
    e1 = e1 / e1.norm()
    return e1, torch.linalg.cross(up, e1)


def azimuths_deg(cameras: Cameras, up: Tensor, center: Tensor, reference: int = 0) -> Tensor:
    """Counter-clockwise azimuth (degrees in [0, 360)) of each camera centre about ``up``."""
    e1, e2 = plane_basis(up.double(), reference)
    v = cameras.centers.double() - center.double()
    return torch.rad2deg(torch.atan2(v @ e2, v @ e1)) % 360


@dataclass
class SectorManifold:
    start_deg: float = 0.0
    width_deg: float = 120.0
    clockwise: bool = True
    up: list[float] | None = None       # None: world +z for Blender-like scenes if given, else estimated
    center: list[float] | None = None   # None: centroid of the given cameras
    reference: int = 0
    kind: str = field(default="sector", init=False)

    def __post_init__(self) -> None:
        if not 0 < self.width_deg <= 360:
            raise ValueError(f"sector width_deg must be in (0, 360], got {self.width_deg}")

    def resolve(self, cameras: Cameras) -> "SectorManifold":
        """Fix up and centre from the scene's cameras (so membership is stable across subsets)."""
        up = self.up if self.up is not None else estimate_up(cameras).tolist()
        center = self.center if self.center is not None else cameras.centers.double().mean(0).tolist()
        return SectorManifold(self.start_deg, self.width_deg, self.clockwise, up, center, self.reference)

    def contains(self, cameras: Cameras) -> Tensor:
        if self.up is None or self.center is None:
            raise ValueError("sector manifold: call resolve(scene cameras) first (up/center unset)")
        up = torch.tensor(self.up, dtype=torch.float64)
        az = azimuths_deg(cameras, up / up.norm(), torch.tensor(self.center, dtype=torch.float64),
                          self.reference)
        offset = (self.start_deg - az) % 360 if self.clockwise else (az - self.start_deg) % 360
        return offset <= self.width_deg + 1e-9

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class PoseListManifold:
    view_ids: list[int]
    kind: str = field(default="poses", init=False)

    def __post_init__(self) -> None:
        if not self.view_ids:
            raise ValueError("poses manifold: view_ids is empty")

    def resolve(self, cameras: Cameras) -> "PoseListManifold":
        return self

    def contains_ids(self, ids: list[int]) -> Tensor:
        wanted = set(self.view_ids)
        return torch.tensor([i in wanted for i in ids], dtype=torch.bool)

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class RegionManifold:
    center: list[float]
    radius: float
    margin_px: float = 0.0
    kind: str = field(default="region", init=False)

    def resolve(self, cameras: Cameras) -> "RegionManifold":
        return self

    def contains(self, cameras: Cameras) -> Tensor:
        """Views whose image holds the whole projected region (the ball's centre +- its radius)."""
        c = torch.tensor(self.center, dtype=torch.float64)
        p = cameras.viewmats[:, :3, :3].double() @ c + cameras.viewmats[:, :3, 3].double()  # [C, 3]
        z = p[:, 2]
        ks = cameras.Ks.double()
        u = ks[:, 0, 0] * p[:, 0] / z.clamp_min(1e-9) + ks[:, 0, 2]
        v = ks[:, 1, 1] * p[:, 1] / z.clamp_min(1e-9) + ks[:, 1, 2]
        r = ks[:, 0, 0] * self.radius / z.clamp_min(1e-9) + self.margin_px
        return (z > self.radius) & (u - r >= 0) & (u + r <= cameras.width) & \
            (v - r >= 0) & (v + r <= cameras.height)

    def to_dict(self) -> dict:
        return asdict(self)


KINDS = {"sector": SectorManifold, "poses": PoseListManifold, "region": RegionManifold}


def manifold_from_dict(data: dict):
    """Build a manifold from its dict form (``kind`` selects the class); unknown keys are errors."""
    data = dict(data)
    kind = data.pop("kind", None)
    if kind not in KINDS:
        raise ValueError(f"manifold kind must be one of {sorted(KINDS)}, got {kind!r}")
    try:
        return KINDS[kind](**data)
    except TypeError as err:
        raise ValueError(f"manifold {kind!r}: bad keys ({err})") from None


def member_ids(manifold, cameras: Cameras, ids: list[int]) -> list[int]:
    """Dataset ids (aligned with ``cameras``) inside the manifold."""
    if isinstance(manifold, PoseListManifold):
        mask = manifold.contains_ids(ids)
    else:
        mask = manifold.contains(cameras)
    return [i for i, m in zip(ids, mask.tolist()) if m]

