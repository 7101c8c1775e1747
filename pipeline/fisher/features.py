"""Per-Gaussian 2D features of a view and their Jacobian w.r.t. the raw parameters.

A raw parameter of Gaussian g reaches the rendered image only through g's own 9 features
(mean2d u, v; conic a, b, c; opacity; colour r, g, b), so the per-view Fisher of the raw
parameters is diag(A^T G A) per Gaussian with A = d features / d raw [9, P] (this module) and G
the 9x9 feature-space Fisher (``exact.py``).
"""

from __future__ import annotations

import torch
from torch import Tensor

from pipeline.splat import Gaussians
from pipeline.splat.project import Projection, project

FEATURES = ("u", "v", "conic_a", "conic_b", "conic_c", "opacity", "r", "g", "b")
PARAM_GROUPS = ("means", "log_scales", "quats", "logit_opacities", "sh0", "shN")


def param_layout(gaussians: Gaussians, groups: tuple[str, ...]) -> list[tuple[str, int]]:
    """(group, width per Gaussian) in the flattened per-Gaussian parameter order."""
    unknown = [g for g in groups if g not in PARAM_GROUPS]
    if unknown:
        raise ValueError(f"unknown parameter groups {unknown}; choose from {PARAM_GROUPS}")
    params = gaussians.params()
    return [(g, params[g][0].numel() if len(gaussians) else 0) for g in PARAM_GROUPS if g in groups]


def feature_jacobian(gaussians: Gaussians, viewmat: Tensor, K: Tensor, width: int, height: int,
                     groups: tuple[str, ...], sh_degree: int | None = None,
                     near: float = 0.01) -> tuple[Projection, Tensor]:
    """Project and return (projection, A [N, 9, P]) with P the selected raw parameters per Gaussian.

    Each feature row depends only on its own Gaussian, so one backward pass per feature (9 in
    all, batched with vmap) gives A for every Gaussian at once.
    """
    leaves = {k: v.detach().clone().requires_grad_(True) for k, v in gaussians.params().items()}
    with torch.enable_grad():
        proj = project(Gaussians(**leaves), viewmat, K, width, height, sh_degree, near)
        feats = torch.cat([proj.means2d, proj.conics, proj.opacities[:, None], proj.colors], dim=1)
        wanted = [leaves[g] for g, _ in param_layout(gaussians, groups)]
        selectors = torch.eye(feats.shape[1], dtype=feats.dtype, device=feats.device)
        selectors = selectors[:, None, :].expand(-1, feats.shape[0], -1)  # [9, N, 9]
        grads = torch.autograd.grad(feats, wanted, selectors, is_grads_batched=True,
                                    allow_unused=True, materialize_grads=True)
        rows = torch.cat([gr.reshape(gr.shape[0], gr.shape[1], -1) for gr in grads], dim=2)
    detached = Projection(*(getattr(proj, f).detach() for f in
                            ("means2d", "conics", "depths", "radii", "colors", "opacities")))
    return detached, rows.transpose(0, 1)  # [N, 9, P]
