"""One door per backend: ``splat_backend(settings, device)`` resolves a backend name once into the
projector and the compositor every caller then uses, so no call site branches on the name.

Each fast op has a slow, obviously correct twin that the tests compare it with:

| op | torch (oracle, any device) | compiled (numba, the CPU production path) |
|---|---|---|
| projection + SH colour | ``project.project`` | ``compiled.project_compiled`` (``project_kernels``) |
| compositing | ``rasterize.rasterize`` (``tiles``); ``reference.rasterize_dense`` / ``rasterize_loop`` (``dense``, ``loop``: tiny scenes) | ``compiled.rasterize_compiled`` (``kernels``) |
| Fisher walk | ``fisher.exact.feature_fisher`` (``ViewWalk``) | ``fisher.exact.feature_fisher_compiled`` |
| feature Jacobian | ``fisher.features.feature_jacobian`` | ``fisher.features.feature_jacobian_compiled`` |
| training view (render + both backwards, one node) | ``training_view.training_view_generic`` | ``training_view.training_view_compiled`` |
| training step's loss and gradients | the training view + ``fit.losses.photometric_loss`` through autograd | ``fit.fused_step.fused_step_gradients`` (no autograd; bit-equal to ``training_view_compiled`` + ``photometric_loss_compiled``) |
| Fisher diagonal per view | ``FeatureJacobian.fisher_diagonal`` of the walk's G | ``fisher.diagonal_kernels.fisher_diagonal`` (``exact.view_fisher_fused`` / ``view_fisher_sparse``) |

The last three are the fused paths: on by default, ``compiled.fused_paths(False)`` turns them off
(the benchmarks' ``compiled-unfused``); ``training_view.fused_training_step`` and
``exact.fused_fisher_available`` resolve them.

The Fisher twins live in ``fisher/`` (which builds on ``splat/``, not the other way round); their
door is ``fisher.exact.fisher_backend``, resolved from the same name.
``auto`` resolves to ``compiled`` on CPU tensors when numba loads, else ``tiles``
(``compiled.resolve_backend``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor

from pipeline.splat.compiled import project_compiled, rasterize_compiled, resolve_backend
from pipeline.splat.project import Projection, project
from pipeline.splat.rasterize import rasterize
from pipeline.splat.reference import rasterize_dense, rasterize_loop

# compositor of each named backend: (means2d, conics, opacities, features, radii, depths, width,
# height, **knobs) -> (features image [H, W, D], alpha [H, W])
COMPOSITORS = {"compiled": rasterize_compiled, "tiles": rasterize, "dense": rasterize_dense,
               "loop": rasterize_loop}
BACKEND_NAMES = ("auto", *COMPOSITORS)


@dataclass(frozen=True)
class SplatBackend:
    """A resolved backend: ``project(gaussians, viewmat, K, width, height, sh_degree, near)`` ->
    ``Projection``; ``composite(means2d, conics, opacities, features, radii, depths, width,
    height)`` -> (image [H, W, D], alpha [H, W]) with the settings' performance knobs bound."""

    name: str
    project: Callable[..., Projection]
    composite: Callable[..., tuple[Tensor, Tensor]]


def splat_backend(settings, device: torch.device) -> SplatBackend:
    """Resolve ``settings.backend`` (a ``RenderSettings``) for tensors on ``device``."""
    name = resolve_backend(settings.backend, device)
    compositor = COMPOSITORS[name]
    knobs = {"tile_size": settings.tile_size}
    if name == "tiles":
        knobs["chunk"] = settings.chunk
    elif name == "dense":
        knobs["pixel_block"] = settings.dense_pixel_block

    def composite(*args):
        return compositor(*args, **knobs)

    return SplatBackend(name, project_compiled if name == "compiled" else project, composite)
