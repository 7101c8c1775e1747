"""Random Gaussian scenes and orbit cameras, for tests, benchmarks and smoke runs."""

from __future__ import annotations

import math

import torch

from pipeline.cameras import Cameras, intrinsics_from_fov, look_at
from pipeline.splat.gaussians import Gaussians, num_sh_bases


def random_scene(n: int, seed: int = 0, sh_degree: int = 1, extent: float = 1.0,
                 dtype: torch.dtype = torch.float32, opacity_range=(0.2, 0.95),
                 scale_range=None) -> Gaussians:
    """``n`` anisotropic, randomly rotated Gaussians with random colours in [-extent, extent]^3.

    Scales default to around the mean spacing of the points, so 30-50 Gaussians overlap per
    pixel like a trained scene.
    """
    gen = torch.Generator().manual_seed(seed)
    spacing = 2 * extent / n ** (1 / 3)
    lo, hi = scale_range or (0.3 * spacing, 1.2 * spacing)
    means = (torch.rand(n, 3, generator=gen, dtype=dtype) * 2 - 1) * extent
    log_scales = torch.log(lo + (hi - lo) * torch.rand(n, 3, generator=gen, dtype=dtype))
    quats = torch.randn(n, 4, generator=gen, dtype=dtype)
    o_lo, o_hi = opacity_range
    logit_opacities = torch.logit(o_lo + (o_hi - o_lo) * torch.rand(n, generator=gen, dtype=dtype))
    sh0 = (torch.rand(n, 1, 3, generator=gen, dtype=dtype) - 0.5) * 3
    shn = 0.2 * torch.randn(n, num_sh_bases(sh_degree) - 1, 3, generator=gen, dtype=dtype)
    return Gaussians(means, log_scales, quats, logit_opacities, sh0, shn)


def orbit_cameras(count: int, width: int, height: int, radius: float = 3.0, elevation_deg=20.0,
                  fov_x: float = 0.9, dtype: torch.dtype = torch.float32, phase: float = 0.0) -> Cameras:
    """``count`` cameras on a circle of ``radius`` around the origin looking at it (+z is up)."""
    az = torch.arange(count, dtype=torch.float64) * (2 * math.pi / count) + phase
    el = torch.as_tensor(elevation_deg, dtype=torch.float64).expand(count) * math.pi / 180
    eyes = torch.stack([radius * torch.cos(el) * torch.cos(az), radius * torch.cos(el) * torch.sin(az),
                        radius * torch.sin(el)], dim=-1)
    viewmats = look_at(eyes, torch.zeros_like(eyes), torch.tensor([0, 0, 1.0], dtype=torch.float64))
    return Cameras(viewmats.to(dtype), intrinsics_from_fov(fov_x, width, height, count, dtype=dtype),
                   width, height)


def sphere_cameras(count: int, width: int, height: int, radius: float = 3.0, seed: int = 0,
                   fov_x: float = 0.9, dtype: torch.dtype = torch.float32,
                   min_elevation_deg: float = -10.0) -> Cameras:
    """``count`` cameras at random directions on the upper part of a sphere, looking at the origin."""
    gen = torch.Generator().manual_seed(seed)
    az = torch.rand(count, generator=gen, dtype=torch.float64) * 2 * math.pi
    lo = math.sin(math.radians(min_elevation_deg))
    sin_el = lo + (0.95 - lo) * torch.rand(count, generator=gen, dtype=torch.float64)
    cos_el = torch.sqrt(1 - sin_el ** 2)
    eyes = radius * torch.stack([cos_el * torch.cos(az), cos_el * torch.sin(az), sin_el], -1)
    viewmats = look_at(eyes, torch.zeros_like(eyes), torch.tensor([0, 0, 1.0], dtype=torch.float64))
    return Cameras(viewmats.to(dtype), intrinsics_from_fov(fov_x, width, height, count, dtype=dtype),
                   width, height)
