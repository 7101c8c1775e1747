"""The training step's render: one view's RGB image with the background, differentiable w.r.t. the
raw parameters, and the screen-space gradient of the means that densification reads.

Two twins behind one contract, ``render_training_view(gaussians, camera, background, sh_degree,
settings) -> TrainingView``:
- ``training_view_generic``: ``render`` (any backend), ``means2d.retain_grad()``; the oracle.
- ``training_view_compiled``: projection, binning, compositing and both backwards in ONE autograd
  node (``_CompiledTrainingView``), NumPy between the kernels, only the colour channels composited
  (``render`` also composites depth, which the loss never reads). Same casts as ``render`` on the
  compiled backend (projection outputs in the parameters' dtype, rows summed into it), so the
  image and every gradient equal that path's to float rounding. Most of a step's torch ops and
  autograd nodes disappear with it (issue 27: a third of a step was spent outside the kernels).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch
from torch import Tensor

from pipeline.cameras import Cameras
from pipeline.splat import compiled
from pipeline.splat.gaussians import Gaussians
from pipeline.splat.render import RenderSettings, render


@dataclass
class TrainingView:
    """image [H, W, 3] (with background, in the graph); radii [N] int64 (0 = culled);
    ``means2d_grad()`` -> [N, 2] dLoss/dmeans2d, valid after ``backward``."""

    image: Tensor
    radii: Tensor
    means2d_grad: Callable[[], Tensor]


def training_view_generic(gaussians: Gaussians, camera: Cameras, background: Tensor,
                          sh_degree: int, settings: RenderSettings) -> TrainingView:
    """The oracle: ``render`` of one camera, the means2d gradient retained in its graph."""
    out = render(gaussians, camera, background, sh_degree, settings)
    means2d = out.means2d[0]
    means2d.retain_grad()
    return TrainingView(out.rgb[0], out.radii[0], lambda: means2d.grad.detach())


class _GradSink:
    """Where the fused backward leaves the means2d gradient (autograd has no output for it)."""

    value: Tensor | None = None


class _CompiledTrainingView(torch.autograd.Function):
    """Raw parameters -> (image [H, W, 3], radii [N]); backward -> raw parameter gradients, with
    dLoss/dmeans2d written to the sink."""

    @staticmethod
    def forward(ctx, means, log_scales, quats, logit_opacities, sh0, shN, camera, background,
                tile_size, sink):
        dtype = means.dtype
        np_dtype = compiled.to_numpy(means[:0]).dtype
        workers = compiled.use_threads()
        arrays = tuple(compiled.to_numpy(x) for x in (means, log_scales, quats, logit_opacities, sh0,
                                                      shN))
        # outputs in the params' dtype (the casts of ``render`` on the compiled backend); culled
        # Gaussians' colours are not computed: no tile lists them
        means2d, conics, depths, radii, colors, opacities = compiled.project_visible_arrays(
            arrays, camera, workers)
        _, _, width, height, _, _ = camera
        bins = compiled.CompiledBins(means2d, conics, opacities, radii, depths, width, height,
                                     tile_size, workers)
        image, final, walked = bins.forward(colors, workers)
        bg = compiled.to_numpy(background)
        alpha = 1 - final.astype(np_dtype)  # as ``rasterize_compiled``: 1 - final, params' dtype
        rgb = image + (1 - alpha)[..., None] * bg
        ctx.arrays, ctx.camera, ctx.bins, ctx.colors = arrays, camera, bins, colors
        ctx.final, ctx.walked, ctx.bg, ctx.sink, ctx.n = final, walked, bg, sink, means.shape[0]
        ctx.dtype = dtype
        radii_t = torch.from_numpy(radii)
        ctx.mark_non_differentiable(radii_t)
        return torch.from_numpy(np.ascontiguousarray(rgb, dtype=np_dtype)), radii_t

    @staticmethod
    def backward(ctx, grad_rgb, _grad_radii):
        kernels, bins = compiled.load(), ctx.bins
        workers = compiled.use_threads()
        g_rgb = compiled.to_numpy(grad_rgb)
        # rgb = image + (1 - alpha) bg with alpha = 1 - final: dL/dfinal = sum_c dL/drgb_c bg_c
        g_final = (g_rgb * ctx.bg).sum(-1)
        row_start, row_ids = bins.walked_rows(ctx.walked)
        rows = kernels.composite_backward(
            bins.gauss_ids, bins.offsets, row_start, row_ids.shape[0], bins.packed, ctx.colors,
            ctx.final, ctx.walked, g_rgb.astype(np.float64), g_final.astype(np.float64),
            bins.tiles_x, bins.tile_size, workers)
        per_gauss = kernels.sum_rows(row_ids, rows, ctx.n, ctx.colors)  # params' dtype
        g_means2d = np.ascontiguousarray(per_gauss[:, 0:2])
        ctx.sink.value = torch.from_numpy(g_means2d)
        f64 = np.float64
        grads = compiled.projection_kernels().project_backward(
            *ctx.arrays, *ctx.camera, g_means2d.astype(f64), per_gauss[:, 2:5].astype(f64),
            np.zeros(ctx.n), per_gauss[:, 6:9].astype(f64), per_gauss[:, 5].astype(f64), workers)
        return (*(torch.from_numpy(x).to(ctx.dtype) for x in grads), None, None, None, None)


def training_view_compiled(gaussians: Gaussians, camera: Cameras, background: Tensor,
                           sh_degree: int, settings: RenderSettings) -> TrainingView:
    """The fused compiled twin of ``training_view_generic`` (CPU tensors only)."""
    from pipeline.splat.project import active_sh_degree
    if compiled.load() is None:
        raise RuntimeError(f"backend 'compiled' cannot load: {compiled.load_error()}")
    degree = active_sh_degree(gaussians, sh_degree)
    camera = camera.to(device=gaussians.means.device, dtype=gaussians.means.dtype)  # as ``render``
    cam = compiled.kernel_camera(camera.viewmats[0], camera.Ks[0], camera.width, camera.height,
                                 degree, settings.near)
    sink = _GradSink()
    image, radii = _CompiledTrainingView.apply(
        gaussians.means, gaussians.log_scales, gaussians.quats, gaussians.logit_opacities,
        gaussians.sh0, gaussians.shN, cam, background.to(gaussians.means.dtype), settings.tile_size,
        sink)
    return TrainingView(image, radii, lambda: sink.value)


def training_view_renderer(settings: RenderSettings, device: torch.device):
    """The twin for ``settings.backend`` on ``device``: fused when it resolves to ``compiled``
    (and ``compiled.fused_paths`` has not turned the fused paths off)."""
    if fused_training_step(settings, device):
        return training_view_compiled
    return training_view_generic


def fused_training_step(settings: RenderSettings, device: torch.device) -> bool:
    """Whether a training step on ``device`` takes the fused compiled paths: the one-node render
    (``training_view_compiled``) and the compiled loss (``fit.losses.photometric_loss_compiled``)."""
    return compiled.resolve_backend(settings.backend, device) == "compiled" and compiled.fused_enabled()
