"""The training step's render: one view's RGB image with the background, differentiable w.r.t. the
raw parameters, and the screen-space gradient of the means that densification reads.

Two twins behind one contract, ``render_training_view(gaussians, camera, background, sh_degree,
settings) -> TrainingView``:
- ``training_view_generic``: ``render`` (any backend), ``means2d.retain_grad()``; the oracle.
- ``training_view_compiled``: projection, binning, compositing and both backwards in ONE autograd
  node (``_CompiledTrainingView``), NumPy between the kernels, only the colour channels composited
  (``render`` also composites depth, which the loss never reads). Same casts as ``render`` on the
  compiled backend (projection outputs in the parameters' dtype, rows summed into it), so the
  image and every gradient equal that path's to float rounding. Its forward and backward are the
  array functions ``compiled_forward`` / ``compiled_backward``, which the trainer's fused step
  (``fit.fused_step``) calls without autograd; this node is that step's autograd twin in tests.
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


@dataclass
class CompiledForward:
    """One view's fused forward as NumPy arrays (what its backward reads): the raw parameters
    ``arrays`` (means, log_scales, quats, logit_opacities, sh0, shN), the kernel ``camera``, the
    bins, the visible colours, final transmittance and walked lengths; rgb [H, W, 3] (with the
    background) and radii [N] int64 are its outputs."""

    arrays: tuple
    camera: tuple
    bins: compiled.CompiledBins
    colors: np.ndarray
    final: np.ndarray
    walked: np.ndarray
    background: np.ndarray
    rgb: np.ndarray
    radii: np.ndarray


def compiled_forward(arrays: tuple, camera: tuple, background: np.ndarray, tile_size: int,
                     workers: int) -> CompiledForward:
    """Projection, binning and compositing of the colour channels (``render``'s casts on the
    compiled backend: projection outputs in the parameters' dtype; culled Gaussians' colours are
    not computed, no tile lists them)."""
    np_dtype = arrays[0].dtype
    means2d, conics, depths, radii, colors, opacities = compiled.project_visible_arrays(
        arrays, camera, workers)
    _, _, width, height, _, _ = camera
    bins = compiled.CompiledBins(means2d, conics, opacities, radii, depths, width, height,
                                 tile_size, workers)
    image, final, walked = bins.forward(colors, workers)
    alpha = 1 - final.astype(np_dtype)  # as ``rasterize_compiled``: 1 - final, params' dtype
    rgb = np.ascontiguousarray(image + (1 - alpha)[..., None] * background, dtype=np_dtype)
    return CompiledForward(arrays, camera, bins, colors, final, walked, background, rgb, radii)


def compiled_backward(fwd: CompiledForward, g_rgb: np.ndarray, workers: int):
    """(raw parameter gradients (6 arrays, the parameters' dtype), dLoss/dmeans2d [N, 2]) from
    dLoss/drgb [H, W, 3]: compositing's backward rows summed per Gaussian into the parameters'
    dtype (as the unfused path's autograd does), then the projection's backward."""
    kernels, bins, n = compiled.load(), fwd.bins, fwd.arrays[0].shape[0]
    # rgb = image + (1 - alpha) bg with alpha = 1 - final: dL/dfinal = sum_c dL/drgb_c bg_c
    g_final = (g_rgb * fwd.background).sum(-1)
    row_start, row_ids = bins.walked_rows(fwd.walked)
    rows = kernels.composite_backward(
        bins.gauss_ids, bins.offsets, row_start, row_ids.shape[0], bins.packed, fwd.colors,
        fwd.final, fwd.walked, g_rgb.astype(np.float64), g_final.astype(np.float64),
        bins.tiles_x, bins.tile_size, workers)
    per_gauss = kernels.sum_rows(row_ids, rows, n, fwd.colors)  # params' dtype
    g_means2d = np.ascontiguousarray(per_gauss[:, 0:2])
    f64 = np.float64
    grads = compiled.projection_kernels().project_backward(
        *fwd.arrays, *fwd.camera, g_means2d.astype(f64), per_gauss[:, 2:5].astype(f64),
        np.zeros(n), per_gauss[:, 6:9].astype(f64), per_gauss[:, 5].astype(f64), workers)
    return grads, g_means2d


class _CompiledTrainingView(torch.autograd.Function):
    """Raw parameters -> (image [H, W, 3], radii [N]); backward -> raw parameter gradients, with
    dLoss/dmeans2d written to the sink."""

    @staticmethod
    def forward(ctx, means, log_scales, quats, logit_opacities, sh0, shN, camera, background,
                tile_size, sink):
        arrays = tuple(compiled.to_numpy(x) for x in (means, log_scales, quats, logit_opacities, sh0,
                                                      shN))
        fwd = compiled_forward(arrays, camera, compiled.to_numpy(background), tile_size,
                               compiled.use_threads())
        ctx.fwd, ctx.sink, ctx.dtype = fwd, sink, means.dtype
        radii_t = torch.from_numpy(fwd.radii)
        ctx.mark_non_differentiable(radii_t)
        return torch.from_numpy(fwd.rgb), radii_t

    @staticmethod
    def backward(ctx, grad_rgb, _grad_radii):
        grads, g_means2d = compiled_backward(ctx.fwd, compiled.to_numpy(grad_rgb),
                                             compiled.use_threads())
        ctx.sink.value = torch.from_numpy(g_means2d)
        return (*(torch.from_numpy(x).to(ctx.dtype) for x in grads), None, None, None, None)


def training_view_compiled(gaussians: Gaussians, camera: Cameras, background: Tensor,
                           sh_degree: int, settings: RenderSettings) -> TrainingView:
    """The fused compiled twin of ``training_view_generic`` (CPU tensors only)."""
    cam = training_camera(gaussians, camera, sh_degree, settings)
    sink = _GradSink()
    image, radii = _CompiledTrainingView.apply(
        gaussians.means, gaussians.log_scales, gaussians.quats, gaussians.logit_opacities,
        gaussians.sh0, gaussians.shN, cam, background.to(gaussians.means.dtype), settings.tile_size,
        sink)
    return TrainingView(image, radii, lambda: sink.value)


def training_camera(gaussians: Gaussians, camera: Cameras, sh_degree: int,
                    settings: RenderSettings) -> tuple:
    """The kernel camera (``compiled.kernel_camera``) of one camera [1] for a fused step: cast to
    the parameters' dtype first, as ``render`` does; the SH degree checked against the stored one."""
    from pipeline.splat.project import active_sh_degree
    if compiled.load() is None:
        raise RuntimeError(f"backend 'compiled' cannot load: {compiled.load_error()}")
    degree = active_sh_degree(gaussians, sh_degree)
    camera = camera.to(device=gaussians.means.device, dtype=gaussians.means.dtype)  # as ``render``
    return compiled.kernel_camera(camera.viewmats[0], camera.Ks[0], camera.width, camera.height,
                                  degree, settings.near)


def fused_training_step(settings: RenderSettings, device: torch.device) -> bool:
    """Whether a training step on ``device`` takes the fused compiled path
    (``fit.fused_step.fused_step_gradients``: this module's array forward and backward and the
    compiled loss, no autograd): when the backend resolves to ``compiled`` and
    ``compiled.fused_paths`` has not turned the fused paths off. Otherwise the step goes through
    autograd with ``training_view_generic`` and the torch loss."""
    return compiled.resolve_backend(settings.backend, device) == "compiled" and compiled.fused_enabled()
