"""Per-Gaussian 2D features of a view and their Jacobian w.r.t. the raw parameters.

A raw parameter of Gaussian g reaches the rendered image only through g's own 9 features
(mean2d u, v; conic a, b, c; opacity; colour r, g, b), so the per-view Fisher of the raw
parameters is diag(A^T G A) per Gaussian with A = d features / d raw [9, P] (this module) and G
the 9x9 feature-space Fisher (``exact.py``).

A is sparse and kept in its structure (``FeatureJacobian``): the geometric parameters (means,
log-scales, quaternions) reach u, v, the conic and (means only, via the view direction) the
colour, which one batched backward of 8 rows gives; the opacity row is sigmoid'; a colour
channel is linear in its SH coefficients with the SH basis at the view direction as slope (zero
where the colour is clamped at 0). Only ``dense()`` builds the full [N, 9, P] matrix.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from pipeline.splat import Gaussians
from pipeline.splat.project import active_sh_degree, project, view_directions
from pipeline.splat.sh import sh_basis

FEATURES = ("u", "v", "conic_a", "conic_b", "conic_c", "opacity", "r", "g", "b")
PARAM_GROUPS = ("means", "log_scales", "quats", "logit_opacities", "sh0", "shN")
GEOMETRIC = ("means", "log_scales", "quats")
GEOMETRIC_ROWS = (0, 1, 2, 3, 4, 6, 7, 8)  # feature rows a geometric parameter can reach
OPACITY_ROW, COLOUR_ROWS = 5, slice(6, 9)


def param_layout(gaussians: Gaussians, groups: tuple[str, ...]) -> list[tuple[str, int]]:
    """(group, width per Gaussian) in the flattened per-Gaussian parameter order."""
    unknown = [g for g in groups if g not in PARAM_GROUPS]
    if unknown:
        raise ValueError(f"unknown parameter groups {unknown}; choose from {PARAM_GROUPS}")
    params = gaussians.params()
    return [(g, params[g].shape[1:].numel()) for g in PARAM_GROUPS if g in groups]


@dataclass
class FeatureJacobian:
    """A = d features / d raw parameters of one view, in its block structure (N Gaussians).

    layout: [(group, width)] of the selected groups (``param_layout``);
    geometry [N, 8, Q]: rows ``GEOMETRIC_ROWS`` w.r.t. the selected geometric groups in layout
    order (Q = their total width, 0 if none); opacity_slope [N] = d opacity / d logit;
    sh_slope [N, K, 3] = d colour_c / d sh_kc (the SH basis, zero beyond the active degree and
    where the colour is clamped).
    """

    layout: list[tuple[str, int]]
    geometry: Tensor
    opacity_slope: Tensor
    sh_slope: Tensor

    def __post_init__(self):
        n = self.opacity_slope.shape[0]
        q = sum(w for g, w in self.layout if g in GEOMETRIC)
        if tuple(self.geometry.shape) != (n, len(GEOMETRIC_ROWS), q):
            raise ValueError(f"feature Jacobian geometry block has shape {tuple(self.geometry.shape)}, "
                             f"expected [N, 8, Q] = {(n, len(GEOMETRIC_ROWS), q)} for layout {self.layout}")
        if self.sh_slope.shape[0] != n or self.sh_slope.shape[2] != 3:
            raise ValueError(f"feature Jacobian SH slope has shape {tuple(self.sh_slope.shape)}, "
                             f"expected [N={n}, K, 3]")

    def column_blocks(self):
        """Yield (group, its column slice in the flattened layout, its column slice in
        ``geometry`` for a geometric group else None)."""
        start, geo_start = 0, 0
        for group, width in self.layout:
            geo = None
            if group in GEOMETRIC:
                geo, geo_start = slice(geo_start, geo_start + width), geo_start + width
            yield group, slice(start, start + width), geo
            start += width

    def _sh_slope(self, group: str) -> Tensor:
        """[N, k, 3] slopes of the coefficients of ``sh0`` (k = 1) or ``shN``."""
        return self.sh_slope[:, :1] if group == "sh0" else self.sh_slope[:, 1:]

    def fisher_diagonal(self, feature_fisher: Tensor) -> Tensor:
        """diag(A^T G A) [N, P] float64 for G [N, 9, 9] float64, block by block."""
        G = feature_fisher
        colour = torch.diagonal(G[:, COLOUR_ROWS, COLOUR_ROWS], dim1=1, dim2=2)  # [N, 3]
        rows = list(GEOMETRIC_ROWS)
        geo = self.geometry.to(G.dtype)
        geo_f = ((G[:, rows][:, :, rows] @ geo) * geo).sum(1)  # [N, Q] (Q = 0: no geometric group)
        out = []
        for group, _, geo_cols in self.column_blocks():
            if geo_cols is not None:
                out.append(geo_f[:, geo_cols])
            elif group == "logit_opacities":
                out.append((G[:, OPACITY_ROW, OPACITY_ROW] * self.opacity_slope.to(G.dtype) ** 2)[:, None])
            else:  # column k * 3 + c is coefficient k of channel c
                sh_f = self._sh_slope(group).to(G.dtype).square() * colour[:, None, :]
                out.append(sh_f.reshape(G.shape[0], -1))
        return torch.cat(out, dim=1)

    def dense(self) -> Tensor:
        """A [N, 9, P] (geometry dtype)."""
        n = self.geometry.shape[0]
        A = self.geometry.new_zeros(n, 9, sum(w for _, w in self.layout))
        for group, cols, geo_cols in self.column_blocks():
            if geo_cols is not None:
                A[:, list(GEOMETRIC_ROWS), cols] = self.geometry[:, :, geo_cols]
            elif group == "logit_opacities":
                A[:, OPACITY_ROW, cols.start] = self.opacity_slope
            else:  # column k * 3 + c is coefficient k of channel c
                for c in range(3):
                    A[:, 6 + c, cols.start + c:cols.stop:3] = self._sh_slope(group)[:, :, c]
        return A

def feature_jacobian(gaussians: Gaussians, viewmat: Tensor, K: Tensor, width: int, height: int,
                     groups: tuple[str, ...], sh_degree: int | None, near: float) -> FeatureJacobian:
    """A = d features / d raw parameters of one view for the selected raw parameter groups."""
    layout = param_layout(gaussians, groups)
    geometric = [g for g, _ in layout if g in GEOMETRIC]
    params = {k: v.detach() for k, v in gaussians.params().items()}
    leaves = {g: params[g].clone().requires_grad_(True) for g in geometric}
    with torch.enable_grad():
        proj = project(Gaussians(**{**params, **leaves}), viewmat, K, width, height, sh_degree, near)
        n = len(gaussians)
        if geometric and n:
            feats = torch.cat([proj.means2d, proj.conics, proj.colors], dim=1)  # [N, 8]
            selectors = torch.eye(8, dtype=feats.dtype, device=feats.device)[:, None, :].expand(-1, n, -1)
            grads = torch.autograd.grad(feats, [leaves[g] for g in geometric], selectors,
                                        is_grads_batched=True)
            geometry = torch.cat([gr.reshape(8, n, -1) for gr in grads], dim=2).transpose(0, 1)
        else:
            geometry = params["means"].new_zeros(n, len(GEOMETRIC_ROWS), 0)
    degree = gaussians.sh_degree if sh_degree is None else sh_degree
    basis = torch.stack(sh_basis(degree, view_directions(params["means"], viewmat)), dim=1)  # [N, k]
    slope = basis.new_zeros(n, gaussians.shN.shape[1] + 1, 3)
    slope[:, :basis.shape[1]] = basis[:, :, None] * (proj.colors.detach() > 0)[:, None, :]
    o = proj.opacities.detach()
    return FeatureJacobian(layout, geometry, o * (1 - o), slope)


# columns of each geometric group in the compiled kernel's [N, 8, 10] geometry block
_KERNEL_COLUMNS = {"means": slice(0, 3), "log_scales": slice(3, 6), "quats": slice(6, 10)}


def feature_jacobian_compiled(gaussians: Gaussians, viewmat: Tensor, K: Tensor, width: int,
                              height: int, groups: tuple[str, ...], sh_degree: int | None,
                              near: float) -> FeatureJacobian:
    """``feature_jacobian`` by the compiled kernel (hand-written chain rule, float64), CPU only."""
    from pipeline.splat import compiled
    from pipeline.splat.project_kernels import feature_jacobian as kernel
    layout = param_layout(gaussians, groups)
    degree = active_sh_degree(gaussians, sh_degree)
    arrays = [compiled.to_numpy(v) for v in gaussians.params().values()]
    geometry, sh_slope, opacity_slope = (torch.from_numpy(x) for x in kernel(
        *arrays, compiled.to_numpy(viewmat.double()), compiled.intrinsics(K),
        int(width), int(height), int(degree), float(near), compiled.use_threads()))
    columns = [_KERNEL_COLUMNS[g] for g, _ in layout if g in GEOMETRIC]
    geometry = torch.cat([geometry[:, :, c] for c in columns], dim=2) if columns else \
        geometry.new_zeros(geometry.shape[0], len(GEOMETRIC_ROWS), 0)
    return FeatureJacobian(layout, geometry, opacity_slope, sh_slope)
