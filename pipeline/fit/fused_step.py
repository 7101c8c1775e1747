"""A training step's loss and raw parameter gradients by the fused compiled kernels, without
autograd: the render (``training_view.compiled_forward``), the compiled loss and both backwards
called directly, so a step builds no graph and runs no autograd engine (at 64 px its Python and
torch bookkeeping was a sizeable part of a step that the kernels take ~6 ms of).

It computes exactly what the autograd twin computes (``training_view_compiled`` followed by
``losses.photometric_loss_compiled`` and ``backward``): the same kernels on the same arrays, the
loss's gradient cast to the image's dtype as that node does, and the loss value as its tensor
holds it (in the image's dtype). Tests compare the two to the bit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from pipeline.cameras import Cameras
from pipeline.fit import loss_kernels
from pipeline.fit.losses import window_taps
from pipeline.splat import compiled
from pipeline.splat.gaussians import Gaussians
from pipeline.splat.render import RenderSettings
from pipeline.splat.training_view import compiled_backward, compiled_forward, training_camera

PARAM_ORDER = ("means", "log_scales", "quats", "logit_opacities", "sh0", "shN")


@dataclass
class StepGradients:
    """loss: the step's loss (rounded to the image's dtype); grads: dLoss/d each raw parameter,
    by name, in its dtype (empty from the trainer's autograd path, which leaves them on the
    parameters); image [H, W, 3] (with the background); radii [N] int64 (0 = culled);
    means2d_grad [N, 2]: dLoss/dmeans2d, which densification reads."""

    loss: float
    grads: dict[str, Tensor]
    image: Tensor
    radii: Tensor
    means2d_grad: Tensor


def fused_step_gradients(params: dict[str, Tensor], camera: Cameras, background: Tensor,
                         sh_degree: int, settings: RenderSettings, target: Tensor,
                         ssim_weight: float, mask: Tensor | None = None) -> StepGradients:
    """Render ``camera`` [1] from the raw ``params`` (CPU), the photometric loss against
    ``target`` [H, W, 3], and the gradients of every raw parameter. ``mask`` [H, W] (1 = kept):
    the loss of the masked render against the masked target (``losses.masked_pair``), so a
    masked-out pixel gives no gradient."""
    if target.shape != (camera.height, camera.width, 3):
        raise ValueError(f"target must be [{camera.height}, {camera.width}, 3], got "
                         f"{tuple(target.shape)}")
    gaussians = Gaussians.unchecked(**params)
    cam = training_camera(gaussians, camera, sh_degree, settings)
    workers = compiled.use_threads()
    arrays = tuple(compiled.to_numpy(params[name]) for name in PARAM_ORDER)
    dtype = arrays[0].dtype
    bg = compiled.to_numpy(background.to(params["means"].dtype))
    fwd = compiled_forward(arrays, cam, bg, settings.tile_size, workers)
    if mask is None:
        value, grad = loss_kernels.photometric_value_and_grad(
            fwd.rgb, compiled.to_numpy(target), float(ssim_weight), window_taps(11, 1.5), workers)
    else:  # d L(rgb * m) / d rgb = m * L'(rgb * m)
        keep = compiled.to_numpy(mask.to(target.dtype))[..., None].astype(fwd.rgb.dtype)
        value, grad = loss_kernels.photometric_value_and_grad(
            fwd.rgb * keep, compiled.to_numpy(target) * keep, float(ssim_weight), window_taps(11, 1.5), workers)
        grad = grad * keep
    grads, g_means2d = compiled_backward(fwd, grad.astype(dtype), workers)
    return StepGradients(float(np.asarray(value, dtype=dtype)),
                         {name: torch.from_numpy(g) for name, g in zip(PARAM_ORDER, grads)},
                         torch.from_numpy(fwd.rgb), torch.from_numpy(fwd.radii),
                         torch.from_numpy(g_means2d))
