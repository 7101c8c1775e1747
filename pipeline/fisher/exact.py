"""The exact per-view diagonal Fisher F_v = diag(J_v^T J_v) of the rendered RGB image.

Sum over pixels AND channels of squared derivatives, for every selected raw parameter
(rotations included). Per (pixel, Gaussian) the derivative of channel c w.r.t. the Gaussian's 9
features is d_pc = [s_pc h_p ; w_p e_c], where s_pc = dI_pc / d(exponent), h_p = d(exponent) /
d(mean2d, conic, opacity) and w_p = alpha T the compositing weight. h_p is a polynomial of degree
<= 2 in tile-local pixel coordinates, h_p = B phi_p, so the pixel sums of d d^T reduce to pixel
moments of degree <= 4, computed with one matmul per chunk:
    G = [[B (sum_p S_p phi phi^T) B^T, B sum_p s_pc w_p phi], [., diag(sum_p w_p^2)]],
    S_p = sum_c s_pc^2.  Then F_raw = diag(A^T G A) per Gaussian (A from ``features.py``).
G is accumulated in float64.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from pipeline.cameras import Cameras
from pipeline.fisher.features import PARAM_GROUPS, feature_jacobian, param_layout
from pipeline.splat import Gaussians, RenderSettings
from pipeline.splat.rasterize import (bin_gaussians, composite_forward, intersection_coeffs,
                                      outside_image, tile_monomials)

# exponents (of x, y) of phi = (x^2, xy, y^2, x, y, 1)
PHI_EXPONENTS = ((2, 0), (1, 1), (0, 2), (1, 0), (0, 1), (0, 0))
MOMENT_EXPONENTS = tuple((a, b) for a in range(5) for b in range(5) if a + b <= 4)  # 15


@dataclass(frozen=True)
class FisherSpec:
    """Which raw parameter groups enter the Fisher (FisherRF's set omits ``quats``)."""

    groups: tuple[str, ...] = PARAM_GROUPS
    sh_degree: int | None = None  # active SH degree; None = stored degree


def _moment_tables(tile_size: int, dtype, device) -> tuple[Tensor, Tensor]:
    """Pixel monomials of degree <= 4 [P, 15] and the index of phi_i phi_j among them [6, 6]."""
    phi = tile_monomials(tile_size, dtype, device)
    x, y = phi[:, 3], phi[:, 4]
    mono = torch.stack([x ** a * y ** b for a, b in MOMENT_EXPONENTS], dim=1)
    lookup = {e: i for i, e in enumerate(MOMENT_EXPONENTS)}
    pair = torch.tensor([[lookup[(ea[0] + eb[0], ea[1] + eb[1])] for eb in PHI_EXPONENTS]
                         for ea in PHI_EXPONENTS], device=device)
    return mono, pair


def _exponent_basis(conics: Tensor, local_means: Tensor, opacities: Tensor) -> Tensor:
    """B [I, 6, 6]: h = d(exponent)/d(u, v, a, b, c, opacity) = B phi per intersection."""
    a, b, c = conics.unbind(-1)
    mx, my = local_means.unbind(-1)
    z, one = torch.zeros_like(a), torch.ones_like(a)
    rows = [
        [z, z, z, a, b, -(a * mx + b * my)],
        [z, z, z, b, c, -(b * mx + c * my)],
        [-0.5 * one, z, z, mx, z, -0.5 * mx * mx],
        [z, -one, z, my, mx, -mx * my],
        [z, z, -0.5 * one, z, my, -0.5 * my * my],
        [z, z, z, z, z, 1 / opacities],
    ]
    return torch.stack([torch.stack(r, -1) for r in rows], -2)


def feature_fisher(proj, width: int, height: int, background: Tensor,
                   settings: RenderSettings = RenderSettings()) -> Tensor:
    """G [N, 9, 9] float64: sum over pixels and channels of d I / d features outer products."""
    n = proj.means2d.shape[0]
    dtype, device = proj.means2d.dtype, proj.means2d.device
    ts = settings.tile_size
    bins = bin_gaussians(proj.means2d, proj.radii, proj.depths, width, height, ts)
    psi = intersection_coeffs(bins, proj.means2d, proj.conics, proj.opacities)
    colors = proj.colors[bins.gauss_ids]  # [I, 3]
    phi = tile_monomials(ts, dtype, device)
    done = outside_image(bins, width, height, device)
    acc, final, records = composite_forward(psi, colors, bins, phi, done, settings.chunk)
    mono, pair = _moment_tables(ts, dtype, device)
    tile = torch.repeat_interleave(torch.arange(bins.num_tiles, device=device), bins.counts)
    centre = torch.stack([(tile % bins.tiles_x) * ts + ts / 2, (tile // bins.tiles_x) * ts + ts / 2],
                         -1).to(dtype)
    g_ids = bins.gauss_ids
    basis = _exponent_basis(proj.conics[g_ids], proj.means2d[g_ids] - centre, proj.opacities[g_ids])
    behind_bg = final[..., None] * background.to(dtype)  # [T, P, 3]
    G = torch.zeros(n, 9, 9, dtype=torch.float64, device=device)
    for rec in records:
        a = rec.active
        f = colors[rec.pos]  # [Ta, K, 3]
        w = rec.alpha * rec.t_excl  # [Ta, P, K]
        wf = w[..., None] * f[:, None]  # [Ta, P, K, 3]
        behind = (acc[a] - rec.acc_before + behind_bg[a])[:, :, None, :]
        suffix = behind - torch.cumsum(wf, dim=2)  # colour composited behind each Gaussian
        s = rec.alpha[..., None] * (rec.t_excl[..., None] * f[:, None]
                                    - suffix / (1 - rec.alpha)[..., None])
        s = s * rec.live[..., None]
        m4 = torch.einsum("tpk,pm->tkm", (s * s).sum(-1), mono)  # [Ta, K, 15]
        m2 = torch.einsum("tpkc,pj->tkjc", s * w[..., None], phi)  # [Ta, K, 6, 3]
        w2 = (w * w).sum(1)  # [Ta, K]
        bk = basis[rec.pos]  # [Ta, K, 6, 6]
        local = torch.zeros(*rec.pos.shape, 9, 9, dtype=dtype, device=device)
        local[..., :6, :6] = bk @ m4[..., pair] @ bk.transpose(-1, -2)
        cross = bk @ m2
        local[..., :6, 6:] = cross
        local[..., 6:, :6] = cross.transpose(-1, -2)
        local[..., 6:, 6:] = torch.diag_embed(w2[..., None].expand(*w2.shape, 3))
        keep = rec.valid.reshape(-1)
        G.index_add_(0, g_ids[rec.pos.reshape(-1)[keep]], local.reshape(-1, 9, 9)[keep].double())
    return G


def view_fisher(gaussians: Gaussians, cameras: Cameras, background: Tensor | None = None,
                spec: FisherSpec = FisherSpec(),
                settings: RenderSettings = RenderSettings()) -> Tensor:
    """Exact diagonal Fisher of each view's RGB image: [C, N, P] float64.

    P = the selected raw parameters per Gaussian in ``param_layout`` order. Gaussians that no
    pixel sees get exactly zero.
    """
    if len(gaussians) == 0:
        raise ValueError("gaussians: cannot compute the Fisher of an empty scene")
    gaussians.validate()
    cams = cameras.to(device=gaussians.means.device, dtype=gaussians.means.dtype)
    bg = gaussians.means.new_zeros(3) if background is None else background
    out = []
    for i in range(len(cams)):
        proj, jac = feature_jacobian(gaussians, cams.viewmats[i], cams.Ks[i], cams.width, cams.height,
                                     spec.groups, spec.sh_degree, settings.near)
        G = feature_fisher(proj, cams.width, cams.height, bg, settings)
        A = jac.double()
        out.append(torch.einsum("nip,nij,njp->np", A, G, A))
    return torch.stack(out)


def flat_names(gaussians: Gaussians, spec: FisherSpec = FisherSpec()) -> list[tuple[str, int]]:
    return param_layout(gaussians, spec.groups)
