"""Initial Gaussians: from a point cloud (3DGS: scale = root mean square distance to the 3 nearest
neighbours) or random."""

from __future__ import annotations

import torch
from torch import Tensor

from pipeline.splat import Gaussians


def knn_rms_distance(points: Tensor, k: int = 3, block: int = 4096) -> Tensor:
    """Root mean square distance of each point [N, 3] to its ``k`` nearest other points, [N]
    (blocked cdist). 3DGS: scales = sqrt(clamp(mean of the 3 squared distances, 1e-7))."""
    n = points.shape[0]
    if n <= 1:
        return points.new_ones(n)
    k = min(k, n - 1)
    out = []
    for start in range(0, n, block):
        d = torch.cdist(points[start:start + block], points)  # [B, N]
        nearest = d.topk(k + 1, largest=False).values[:, 1:]  # drop the point itself
        out.append(nearest.square().mean(dim=1).clamp_min(1e-7).sqrt())
    return torch.cat(out)


def from_point_cloud(points: Tensor, colors: Tensor, sh_degree: int, opacity: float = 0.1) -> Gaussians:
    """Gaussians on ``points`` [N, 3] with ``colors`` [N, 3] in [0, 1]."""
    if points.ndim != 2 or points.shape[1] != 3 or points.shape[0] == 0:
        raise ValueError(f"points must be a non-empty [N, 3] tensor, got {tuple(points.shape)}")
    if colors.shape != points.shape:
        raise ValueError(f"colors must match points {tuple(points.shape)}, got {tuple(colors.shape)}")
    scale = knn_rms_distance(points)
    return Gaussians.from_points(points, colors, sh_degree, scale, opacity)


def random_in_box(n: int, low: Tensor, high: Tensor, sh_degree: int, seed: int = 0,
                  opacity: float = 0.1) -> Gaussians:
    """``n`` Gaussians uniform in the box [low, high], random colours, kNN-based scales."""
    gen = torch.Generator().manual_seed(seed)
    points = low + torch.rand(n, 3, generator=gen, dtype=low.dtype) * (high - low)
    colors = torch.rand(n, 3, generator=gen, dtype=low.dtype)
    return from_point_cloud(points, colors, sh_degree, opacity)
