"""Render Gaussians into a batch of cameras: projection, then tiled (or dense) compositing."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from pipeline.cameras import Cameras
from pipeline.splat.backend import BACKEND_NAMES, splat_backend
from pipeline.splat.gaussians import Gaussians


@dataclass
class RenderOutput:
    """rgb [C, H, W, 3] with background; alpha [C, H, W] accumulated opacity; depth [C, H, W]
    expected camera z of the composited Gaussians (normalised by alpha, 0 where alpha is 0);
    means2d: per camera the [N, 2] tensor used in the graph (call ``retain_grad`` on it before
    backward to read screen-space gradients for densification); radii [C, N] int (0 = culled)."""

    rgb: Tensor
    alpha: Tensor
    depth: Tensor
    means2d: list[Tensor]
    radii: Tensor


@dataclass(frozen=True)
class RenderSettings:
    near: float = 0.01
    tile_size: int = 8
    chunk: int = 64
    backend: str = "auto"
    dense_pixel_block: int | None = None  # dense oracle only: checkpointed pixel blocks

    def __post_init__(self):
        if self.backend not in BACKEND_NAMES:
            raise ValueError(f"backend must be one of {list(BACKEND_NAMES)}, got {self.backend!r}")


def render(gaussians: Gaussians, cameras: Cameras, background: Tensor | None = None,
           sh_degree: int | None = None, settings: RenderSettings = RenderSettings(),
           extra_features: Tensor | None = None) -> RenderOutput:
    """Render ``gaussians`` into every camera of ``cameras``.

    background: [3] colour added as (1 - alpha) * background (default black).
    extra_features: optional [N, E] per-Gaussian values composited alongside the colour; they are
    returned as channels 3.. of ``rgb`` (without background), for variance/uncertainty renders.
    """
    if len(gaussians) == 0:
        raise ValueError("gaussians: cannot render an empty scene (N = 0)")
    gaussians.validate()
    backend = splat_backend(settings, gaussians.means.device)
    cams = cameras.to(device=gaussians.means.device, dtype=gaussians.means.dtype)
    if background is None:
        background = gaussians.means.new_zeros(3)
    if background.shape != (3,):
        raise ValueError(f"background must be [3], got {tuple(background.shape)}")
    outputs = []
    for i in range(len(cams)):
        proj = backend.project(gaussians, cams.viewmats[i], cams.Ks[i], cams.width, cams.height,
                         sh_degree, settings.near)
        feats = [proj.colors, proj.depths[:, None]]
        if extra_features is not None:
            feats.append(extra_features)
        image, alpha = backend.composite(proj.means2d, proj.conics, proj.opacities, torch.cat(feats, 1),
                                         proj.radii, proj.depths, cams.width, cams.height)
        rgb = image[..., :3] + (1 - alpha)[..., None] * background
        depth = torch.where(alpha > 0, image[..., 3] / alpha.clamp_min(1e-10), torch.zeros_like(alpha))
        if extra_features is not None:
            rgb = torch.cat([rgb, image[..., 4:]], dim=-1)
        outputs.append((rgb, alpha, depth, proj.means2d, proj.radii))
    rgbs, alphas, depths, means2ds, radiis = zip(*outputs)
    return RenderOutput(torch.stack(rgbs), torch.stack(alphas), torch.stack(depths), list(means2ds),
                        torch.stack(radiis))
