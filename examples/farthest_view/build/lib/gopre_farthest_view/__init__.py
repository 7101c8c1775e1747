"""``farthest_view``: pick the candidate whose viewing direction is farthest (in angle) from
every taken view's, greedily for a batch. Written only against ``pipeline.api``.

The score of a candidate is the smallest angle, in degrees, between its optical axis and the
optical axis of any taken view (higher is better); ties go to the lowest dataset id.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from pipeline.api import API_VERSION, Cameras, Selection, SelectionContext, timed_selection

REQUIRES_API = "1."  # the major version this strategy was written against
if not API_VERSION.startswith(REQUIRES_API):
    raise ImportError(f"gopre-farthest-view needs gopre's API {REQUIRES_API}x, found {API_VERSION}")


def optical_axes(cameras: Cameras) -> torch.Tensor:
    """[C, 3] unit viewing directions in world space (OpenCV: the camera looks along +z)."""
    rotations = cameras.viewmats[:, :3, :3].double()  # world -> camera
    return rotations[:, 2, :] / rotations[:, 2, :].norm(dim=1, keepdim=True)


@dataclass
class FarthestView:
    name: str = "farthest_view"
    min_angle_deg: float = 0.0    # candidates closer than this to a taken view score 0

    def __post_init__(self) -> None:
        if not 0.0 <= self.min_angle_deg < 180.0:
            raise ValueError(f"farthest_view min_angle_deg must be in [0, 180), got {self.min_angle_deg}")

    def select(self, ctx: SelectionContext, count: int = 1) -> Selection:
        def run(order: list[int]):
            axes = optical_axes(ctx.candidates)[order]                        # [M, 3]
            taken = optical_axes(ctx.taken) if len(ctx.taken) else axes[:0]   # [T, 3]
            nearest = (_angles(axes, taken).min(1).values if len(taken)
                       else torch.full((len(order),), 180.0, dtype=torch.float64))
            nearest = torch.where(nearest < self.min_angle_deg, torch.zeros_like(nearest), nearest)
            first, picks = nearest.clone(), []
            for _ in range(min(count, len(order))):
                best = int(torch.argmax(nearest))  # the first maximum: the lowest dataset id
                picks.append(best)
                nearest = torch.minimum(nearest, _angles(axes, axes[best:best + 1])[:, 0])
                nearest[picks] = -1.0
            return picks, first
        return timed_selection(ctx, run)


def _angles(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """[A, B] angles in degrees between unit vectors."""
    return torch.rad2deg(torch.arccos((a @ b.T).clamp(-1.0, 1.0)))
