"""A space of camera poses to search: the shell of look-at poses around a scene centre.

A pose is three numbers ``(azimuth_deg, elevation_deg, radius)``: the camera sits at
``centre + radius * (cos(el) (cos(az) e1 + sin(az) e2) + sin(el) up)`` and looks at the centre with
``up`` up in its image. ``e1, e2`` is ``data.manifolds.plane_basis(up, reference)``, so the azimuth
is the one ``SectorManifold`` measures (counter-clockwise about ``up`` from the in-plane direction
of a world axis): a sector-restricted shell holds exactly the poses the sector manifold contains.

The search works in the unit cube: ``unit`` in [0, 1]^3 maps linearly onto the azimuth span, the
elevation range and the radius range (``poses_of_unit``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch
from torch import Tensor

from pipeline.cameras import Cameras, look_at
from pipeline.data.manifolds import SectorManifold, azimuths_deg, plane_basis


@dataclass(frozen=True)
class LookAtShell:
    centre: tuple[float, float, float]
    up: tuple[float, float, float]            # unit
    azimuth_start_deg: float                  # the span runs counter-clockwise from here
    azimuth_span_deg: float                   # (0, 360]
    elevation_deg: tuple[float, float]        # [lo, hi] within (-90, 90)
    radius: tuple[float, float]               # [lo, hi], lo > scene_radius
    K: tuple[tuple[float, ...], ...]          # [3, 3] intrinsics of every pose
    width: int
    height: int
    reference: int = 0
    scene_radius: float = 0.0                 # the scene's bounding radius about the centre

    def __post_init__(self) -> None:
        if not 0 < self.azimuth_span_deg <= 360:
            raise ValueError(f"pose space azimuth_span_deg must be in (0, 360], got {self.azimuth_span_deg}")
        lo, hi = self.elevation_deg
        if not -90 < lo <= hi < 90:
            raise ValueError(f"pose space elevation_deg must be a range [lo, hi] within (-90, 90), "
                             f"got {list(self.elevation_deg)}")
        lo, hi = self.radius
        if not 0 < lo <= hi:
            raise ValueError(f"pose space radius must be a range [lo, hi] with 0 < lo <= hi, got {list(self.radius)}")
        if lo <= self.scene_radius:
            raise ValueError(f"pose space radius: its lower end {lo:.4g} is inside the scene (bounding "
                             f"radius {self.scene_radius:.4g} about the centre)")
        up = torch.tensor(self.up, dtype=torch.float64)
        if abs(float(up.norm()) - 1) > 1e-6:
            raise ValueError(f"pose space up must be a unit vector, got {list(self.up)}")
        if self.width < 1 or self.height < 1:
            raise ValueError(f"pose space image size must be positive, got {self.width} x {self.height}")

    # -- construction --------------------------------------------------------------------------
    @staticmethod
    def spanning(cameras: Cameras, centre: Tensor, up: Tensor, scene_radius: float = 0.0,
                 reference: int = 0, full_circle_gap_deg: float = 90.0,
                 full_circle: bool | None = None) -> "LookAtShell":
        """The shell the dataset's ``cameras`` span: their elevation and radius ranges; the full
        circle of azimuths when no gap between neighbouring cameras exceeds
        ``full_circle_gap_deg`` (an object captured all round), else the arc they cover (the
        complement of the largest gap: a real capture's region); ``full_circle`` True or False
        decides it instead (an object scene is a full shell however few its cameras). The poses
        share the first camera's intrinsics and image size."""
        up = up.double() / up.double().norm()
        az, el, r = pose_coordinates(cameras, centre, up, reference)
        ordered = torch.sort(az).values
        gaps = torch.cat([ordered[1:] - ordered[:-1], (ordered[:1] + 360) - ordered[-1:]])
        largest = int(torch.argmax(gaps))
        whole = float(gaps[largest]) <= full_circle_gap_deg if full_circle is None else full_circle
        if whole:
            start, span = 0.0, 360.0
        else:  # the arc from the camera after the largest gap, counter-clockwise to the one before it
            start = float(ordered[(largest + 1) % len(ordered)])
            span = max(360.0 - float(gaps[largest]), 1e-6)
        return LookAtShell(tuple(centre.double().tolist()), tuple(up.tolist()), start, span,
                           (float(el.min()), float(el.max())), (float(r.min()), float(r.max())),
                           tuple(tuple(row) for row in cameras.Ks[0].double().tolist()), cameras.width,
                           cameras.height, reference, scene_radius)

    def within_sector(self, sector: SectorManifold) -> "LookAtShell":
        """The same shell restricted to a resolved sector's azimuths (the goal protocol). The
        sector must share this shell's up, reference and centre up to a shift along up (then it
        measures the same azimuths)."""
        if sector.up is None or sector.center is None:
            raise ValueError("pose space: resolve the sector manifold first (its up and centre are unset)")
        up = torch.tensor(self.up, dtype=torch.float64)
        sector_up = torch.tensor(sector.up, dtype=torch.float64)
        offset = torch.tensor(sector.center, dtype=torch.float64) - torch.tensor(self.centre, dtype=torch.float64)
        in_plane = offset - (offset @ up) * up  # centres that differ along up measure the same azimuths
        same = (torch.allclose(sector_up / sector_up.norm(), up, atol=1e-6)
                and float(in_plane.norm()) <= 1e-6 * max(1.0, float(offset.norm()))
                and sector.reference == self.reference)
        if not same:
            raise ValueError("pose space: the sector's up, centre (in the plane) or reference differ from the shell's")
        if self.azimuth_span_deg < 360:
            raise ValueError("pose space: a sector restricts a full-circle shell only")
        start = sector.start_deg - sector.width_deg if sector.clockwise else sector.start_deg
        return replace(self, azimuth_start_deg=start % 360, azimuth_span_deg=sector.width_deg)

    # -- poses ---------------------------------------------------------------------------------
    def poses_of_unit(self, unit: Tensor) -> Tensor:
        """[B, 3] unit-cube points -> [B, 3] (azimuth_deg, elevation_deg, radius); clamped to the cube."""
        u = unit.double().clamp(0, 1)
        az = (self.azimuth_start_deg + u[:, 0] * self.azimuth_span_deg) % 360
        el = self.elevation_deg[0] + u[:, 1] * (self.elevation_deg[1] - self.elevation_deg[0])
        r = self.radius[0] + u[:, 2] * (self.radius[1] - self.radius[0])
        return torch.stack([az, el, r], 1)

    def unit_of_poses(self, poses: Tensor) -> Tensor:
        """The inverse of ``poses_of_unit`` for poses inside the space: [B, 3] -> [B, 3]."""
        p = poses.double()
        du = ((p[:, 0] - self.azimuth_start_deg) % 360) / self.azimuth_span_deg
        span_el = self.elevation_deg[1] - self.elevation_deg[0]
        span_r = self.radius[1] - self.radius[0]
        dv = (p[:, 1] - self.elevation_deg[0]) / span_el if span_el > 0 else torch.zeros_like(du)
        dw = (p[:, 2] - self.radius[0]) / span_r if span_r > 0 else torch.zeros_like(du)
        return torch.stack([du, dv, dw], 1)

    def contains(self, poses: Tensor, tol: float = 1e-6) -> Tensor:
        """[B] bool: each (azimuth, elevation, radius) inside the space."""
        p = poses.double()
        offset = (p[:, 0] - self.azimuth_start_deg) % 360
        in_az = (offset <= self.azimuth_span_deg + tol) | (offset >= 360 - tol)
        in_el = (p[:, 1] >= self.elevation_deg[0] - tol) & (p[:, 1] <= self.elevation_deg[1] + tol)
        in_r = (p[:, 2] >= self.radius[0] - tol) & (p[:, 2] <= self.radius[1] + tol)
        return in_az & in_el & in_r

    def cameras(self, poses: Tensor) -> Cameras:
        """Cameras [B] at ``poses`` [B, 3] (float32, as the datasets' cameras)."""
        up = torch.tensor(self.up, dtype=torch.float64)
        centre = torch.tensor(self.centre, dtype=torch.float64)
        e1, e2 = plane_basis(up, self.reference)
        az, el, r = (torch.deg2rad(poses[:, 0].double()), torch.deg2rad(poses[:, 1].double()),
                     poses[:, 2].double())
        direction = (torch.cos(el)[:, None] * (torch.cos(az)[:, None] * e1 + torch.sin(az)[:, None] * e2)
                     + torch.sin(el)[:, None] * up)
        eyes = centre + r[:, None] * direction  # [B, 3]
        viewmats = look_at(eyes, centre.expand_as(eyes), up)
        K = torch.tensor(self.K, dtype=torch.float64).expand(len(poses), 3, 3)
        return Cameras(viewmats.float(), K.float().contiguous(), self.width, self.height)

    def poses_of(self, cameras: Cameras) -> Tensor:
        """The (azimuth_deg, elevation_deg, radius) [C, 3] of cameras' centres in this shell's frame
        (the inverse of ``cameras`` for a camera on the shell; any camera has coordinates)."""
        az, el, r = pose_coordinates(cameras, torch.tensor(self.centre), torch.tensor(self.up), self.reference)
        return torch.stack([az, el, r], 1)

    def sample(self, count: int, generator: torch.Generator) -> Tensor:
        """``count`` poses uniform in the unit cube (azimuth, elevation, radius), [count, 3]."""
        return self.poses_of_unit(torch.rand(count, 3, generator=generator, dtype=torch.float64))

    def to_dict(self) -> dict:
        return {"centre": list(self.centre), "up": list(self.up), "azimuth_start_deg": self.azimuth_start_deg,
                "azimuth_span_deg": self.azimuth_span_deg, "elevation_deg": list(self.elevation_deg),
                "radius": list(self.radius), "width": self.width, "height": self.height,
                "reference": self.reference, "scene_radius": self.scene_radius}


def pose_coordinates(cameras: Cameras, centre: Tensor, up: Tensor, reference: int = 0
                     ) -> tuple[Tensor, Tensor, Tensor]:
    """Each camera centre's (azimuth_deg [C], elevation_deg [C], radius [C]) about ``centre``."""
    up = up.double() / up.double().norm()
    v = cameras.centers.double() - centre.double()
    r = v.norm(dim=1)
    el = torch.rad2deg(torch.asin((v @ up / r.clamp_min(1e-300)).clamp(-1, 1)))
    return azimuths_deg(cameras, up, centre, reference), el, r
