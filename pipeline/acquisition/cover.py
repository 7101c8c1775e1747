"""``cover``: COVER, the view-coverage score of NBV-Gym (CVPR 2026), written from its paper and its
public code (``chengine/nbv_gym``, ``nbv_gym/util/coverage.py`` and ``model.py``), not copied.

Each Gaussian g keeps a histogram c_g [G] over G unit directions b_1..b_G spread on the sphere by
a Fibonacci lattice (G = 128, NBV-Gym's ``n_sphere_bins``). Every taken view adds one count to the
bin nearest (largest dot product) to the direction camera centre -> Gaussian, for every Gaussian
in that view's frustum (projected in front of the near plane, on the image, with a pixel radius
above ``radius_clip``; NBV-Gym counts frustum membership, not occlusion or compositing weight).
The counts are rebuilt from all taken views with the current model every round.

A candidate camera scores each Gaussian by how close its viewing direction d_g is to a direction
that has already been seen,
    x_g = max_{k : c_gk > 0} (1 + d_g . b_k) / 2        (0 when the Gaussian was never seen),
alpha-T composites x into the candidate's image, and averages it over the pixels that any
Gaussian reaches (accumulated opacity > 0). The pick is the lowest score: the view whose content
is seen from the least-covered directions. A candidate that reaches no pixel scores +inf (it
would show nothing; NBV-Gym divides by zero there). Batches take the ``count`` lowest scores
(NBV-Gym's top-k, no update between picks).

NBV-Gym can restrict the candidates to the ``neighbours`` nearest to the last taken view (a
KD-tree on camera centres, off in its pipeline's defaults); ``neighbours=None`` (the default)
scores the whole pool like every other strategy here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from pipeline.bounds import FLOAT, INT, bounded, require_bounds
from pipeline.acquisition.base import Selection, SelectionContext, timed_selection
from pipeline.cameras import Cameras
from pipeline.splat import Gaussians, RenderSettings, render
from pipeline.splat.project import project

COVER_BINS = 128          # NBV-Gym NBVSplatModelConfig.n_sphere_bins
COVER_RADIUS_CLIP = 3.0   # NBV-Gym's radius_clip (pixels) when it counts a view's frustum


def fibonacci_directions(count: int) -> Tensor:
    """``count`` unit vectors [G, 3] float64 on a Fibonacci lattice: z_i = 1 - 2 (i + 1/2) / G,
    azimuth 2 pi frac(i / phi) (phi the golden ratio)."""
    if count < 1:
        raise ValueError(f"cover: the number of direction bins must be >= 1, got {count}")
    i = torch.arange(count, dtype=torch.float64)
    z = 1.0 - 2.0 * (i + 0.5) / count
    r = torch.sqrt(torch.clamp(1.0 - z * z, min=0.0))
    golden = (1.0 + math.sqrt(5.0)) / 2.0
    azimuth = 2.0 * math.pi * torch.remainder(i / golden, 1.0)
    return torch.stack([r * torch.cos(azimuth), r * torch.sin(azimuth), z], dim=-1)


def gaussian_directions(means: Tensor, center: Tensor) -> Tensor:
    """Unit directions camera centre -> Gaussian [N, 3] float64 (means [N, 3], center [3])."""
    return torch.nn.functional.normalize(means.double() - center.double(), dim=-1)


def frustum_members(gaussians: Gaussians, camera: Cameras, settings: RenderSettings,
                    radius_clip: float) -> Tensor:
    """[N] bool: the Gaussians one camera's projection keeps with a pixel radius above
    ``radius_clip`` (in front of the near plane and overlapping the image)."""
    cam = camera.to(device=gaussians.means.device, dtype=gaussians.means.dtype)
    proj = project(gaussians, cam.viewmats[0], cam.Ks[0], cam.width, cam.height, 0, settings.near)
    return proj.radii > radius_clip


def direction_counts(gaussians: Gaussians, taken: Cameras, bins: Tensor, settings: RenderSettings,
                     radius_clip: float = COVER_RADIUS_CLIP) -> Tensor:
    """Per-Gaussian histogram [N, G] float64 of the directions the taken views saw it from."""
    g = gaussians.detach()
    counts = torch.zeros(len(g), len(bins), dtype=torch.float64)
    with torch.no_grad():
        for i in range(len(taken)):
            seen = frustum_members(g, taken[i], settings, radius_clip).cpu()
            dirs = gaussian_directions(g.means.cpu()[seen], taken.centers[i].cpu())
            nearest = (dirs @ bins.T).argmax(dim=1)
            counts[seen.nonzero()[:, 0], nearest] += 1.0
    return counts


def coverage_values(counts: Tensor, directions: Tensor, bins: Tensor) -> Tensor:
    """x_g = max over the seen bins of (1 + d_g . b_k) / 2, 0 for a never-seen Gaussian, [N].

    counts [N, G]; directions [N, 3] unit candidate view directions; bins [G, 3]."""
    closeness = (1.0 + directions @ bins.T) / 2.0  # [N, G] in [0, 1]
    return torch.where(counts > 0, closeness, torch.zeros_like(closeness)).amax(dim=1)


def cover_score(gaussians: Gaussians, camera: Cameras, values: Tensor,
                settings: RenderSettings) -> float:
    """The composited coverage of one camera averaged over the pixels with accumulated opacity
    > 0; +inf when no pixel is reached."""
    g = gaussians.detach()
    with torch.no_grad():
        out = render(g, camera, settings=settings, extra_features=values[:, None].to(g.means.dtype))
    image, reached = out.rgb[0, ..., 3].double(), out.alpha[0] > 0
    if not bool(reached.any()):
        return math.inf
    return float(image[reached].sum() / reached.sum())


def nearest_candidates(candidates: Tensor, last_taken: Tensor, neighbours: int) -> list[int]:
    """Positions of the ``neighbours`` candidate centres [M, 3] nearest to ``last_taken`` [3]
    (ties to the lower position), sorted."""
    distance = (candidates.double() - last_taken.double()).norm(dim=1)
    keep = torch.argsort(distance, stable=True)[:neighbours]
    return sorted(keep.tolist())


@dataclass
class CoverStrategy:
    name: str = "cover"
    bins: int = bounded(COVER_BINS, INT, ge=1, usual_max=100_000)
    radius_clip: float = bounded(COVER_RADIUS_CLIP, FLOAT, ge=0)  # pixels
    neighbours: int | None = bounded(None, INT, ge=1, nullable=True)

    def __post_init__(self) -> None:
        require_bounds(self)

    def scores(self, ctx: SelectionContext, order: list[int]) -> Tensor:
        """Every candidate's score [M] (aligned with ``order``); candidates outside the
        neighbourhood of the last taken view, when one is set, score +inf."""
        bins = fibonacci_directions(self.bins)
        counts = direction_counts(ctx.gaussians, ctx.taken, bins, ctx.settings, self.radius_clip)
        pool = ctx.candidates[order]
        scored = list(range(len(order)))
        if self.neighbours is not None and len(ctx.taken):
            scored = nearest_candidates(pool.centers, ctx.taken.centers[-1], self.neighbours)
        means = ctx.gaussians.means.detach().cpu()
        scores = torch.full((len(order),), math.inf, dtype=torch.float64)
        for i in scored:
            values = coverage_values(counts, gaussian_directions(means, pool.centers[i].cpu()), bins)
            scores[i] = cover_score(ctx.gaussians, pool[i], values.to(ctx.gaussians.means.device),
                                    ctx.settings)
        return scores

    def select(self, ctx: SelectionContext, count: int = 1) -> Selection:
        def run(order):
            scores = self.scores(ctx, order)
            return torch.argsort(scores, stable=True)[:count].tolist(), scores
        return timed_selection(ctx, run)
