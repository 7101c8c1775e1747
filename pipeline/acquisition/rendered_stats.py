"""Per-Gaussian image statistics by compositing: sum_p w_pg q_p for any per-pixel map q.

The rendered value of a per-Gaussian feature x is sum_g w_pg x_g, so the gradient of
sum_p q_p * render(x)_p w.r.t. x is exactly sum_p w_pg q_p (w = alpha T, the 3DGS weights).
Features composite over nothing (the background colour only enters the RGB channels, which these
helpers do not read), so they take no background.
"""

from __future__ import annotations

import torch
from torch import Tensor

from pipeline.cameras import Cameras
from pipeline.splat import Gaussians, RenderSettings, render
from pipeline.splat.project import project
from pipeline.splat.rasterize import CompositingWeights, compositing_weights


def weighted_pixel_sums(gaussians: Gaussians, camera: Cameras, pixel_maps: Tensor,
                        settings: RenderSettings) -> Tensor:
    """For one camera and Q per-pixel maps [Q, H, W], return [N, Q] sums sum_p w_pg q_p."""
    q = pixel_maps.shape[0]
    probe = gaussians.means.new_zeros(len(gaussians), q, requires_grad=True)
    with torch.enable_grad():
        out = render(gaussians.detach(), camera, settings=settings, extra_features=probe)
        extra = out.rgb[0, ..., 3:]  # [H, W, Q]
        (grad,) = torch.autograd.grad((extra * pixel_maps.permute(1, 2, 0)).sum(), probe)
    return grad


def render_feature(gaussians: Gaussians, cameras: Cameras, values: Tensor,
                   settings: RenderSettings) -> Tensor:
    """Alpha-composite per-Gaussian values [N] (or [C, N], one row per camera) into [C, H, W]."""
    out = []
    for i in range(len(cameras)):
        v = values[i] if values.ndim == 2 else values
        with torch.no_grad():
            r = render(gaussians.detach(), cameras[i], settings=settings,
                       extra_features=v[:, None].to(gaussians.means.dtype))
        out.append(r.rgb[0, ..., 3])
    return torch.stack(out)


@torch.no_grad()
def view_compositing_weights(gaussians: Gaussians, camera: Cameras,
                             settings: RenderSettings) -> CompositingWeights:
    """The sparse compositing weights w_pg = alpha T of one camera (``splat.rasterize``)."""
    if len(camera) != 1:
        raise ValueError(f"view_compositing_weights takes one camera, got {len(camera)}")
    cam = camera.to(device=gaussians.means.device, dtype=gaussians.means.dtype)
    proj = project(gaussians.detach(), cam.viewmats[0], cam.Ks[0], cam.width, cam.height, 0,
                   settings.near)
    return compositing_weights(proj.means2d, proj.conics, proj.opacities, proj.radii, proj.depths,
                               cam.width, cam.height, settings.tile_size, settings.chunk)
