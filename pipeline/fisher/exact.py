"""The exact per-view diagonal Fisher F_v = diag(J_v^T J_v) of the rendered RGB image.

Sum over pixels AND channels of squared derivatives, for every selected raw parameter
(rotations included). Per (pixel, Gaussian) the derivative of channel c w.r.t. the Gaussian's 9
features is d_pc = [s_pc h_p ; w_p e_c], where s_pc = dI_pc / d(exponent), h_p = d(exponent) /
d(mean2d, conic, opacity) and w_p = alpha T the compositing weight. h_p is a polynomial of degree
<= 2 in the pixel's offset from the Gaussian's mean, h_p = C psi(d_p), so the pixel sums of
d d^T reduce to pixel moments of degree <= 4:
    G = [[C (sum_p S_p psi psi^T) C^T, C sum_p s_pc w_p psi], [., diag(sum_p w_p^2)]],
    S_p = sum_c s_pc^2.  Then F_raw = diag(A^T G A) per Gaussian (A from ``features.py``).
The moments come from one matmul per depth chunk in tile-local coordinates, are shifted to the
Gaussian's mean (``centre_moments``) and summed per Gaussian in float64; C is applied once per
Gaussian. Only the intersections the walk reaches (early termination) and the Gaussians they
belong to are touched; every other Gaussian has exactly zero Fisher.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import torch
from torch import Tensor

from pipeline.cameras import Cameras
from pipeline.fisher.features import (PARAM_GROUPS, FeatureJacobian, feature_jacobian,
                                      feature_jacobian_compiled, param_layout)
from pipeline.splat import Gaussians, RenderSettings, compiled
from pipeline.splat.project import active_sh_degree, project
from pipeline.splat.rasterize import (bin_gaussians, composite_forward, intersection_coeffs,
                                      local_means, outside_image, tile_monomials, untile)

# exponents (of x, y) of phi = (x^2, xy, y^2, x, y, 1)
PHI_EXPONENTS = ((2, 0), (1, 1), (0, 2), (1, 0), (0, 1), (0, 0))
MOMENT_EXPONENTS = tuple((a, b) for a in range(5) for b in range(5) if a + b <= 4)  # 15


HESSIANS = ("exact", "fisherrf_released")


@dataclass(frozen=True)
class FisherSpec:
    """Which raw parameter groups enter the Fisher (FisherRF's set omits ``quats``), and which
    Hessian: ``exact`` = diag(J^T J), channels squared separately; ``fisherrf_released`` = the
    released FisherRF kernel's: geometry and opacity entries square the channel-summed image
    derivative w.r.t. the *activated* parameter (scale = exp, opacity = sigmoid) and carry the
    activation's derivative once, not squared; SH entries are per-channel sums of squares (exact).
    """

    groups: tuple[str, ...] = PARAM_GROUPS
    sh_degree: int | None = None  # active SH degree; None = stored degree
    hessian: str = "exact"

    def __post_init__(self) -> None:
        if self.hessian not in HESSIANS:
            raise ValueError(f"Fisher hessian must be one of {HESSIANS}, got {self.hessian!r}")

    @property
    def channel_summed(self) -> bool:
        return self.hessian == "fisherrf_released"


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


def _centred_basis(conics: Tensor, opacities: Tensor) -> Tensor:
    """C [N, 6, 6]: h = C psi(d) per Gaussian, where psi(d) = (dx^2, dx dy, dy^2, dx, dy, 1) of
    d = pixel - mean2d (``_exponent_basis`` at a zero offset)."""
    return _exponent_basis(conics, conics.new_zeros(conics.shape[0], 2), opacities)


def centre_moments(moments: Tensor, offsets: Tensor, exponents: tuple) -> Tensor:
    """Shift pixel moments to per-row origins by the binomial theorem (exact).

    moments [E, I, ...]: row e = (a, b) holds sum_p w_p x_p^a y_p^b; ``exponents`` lists the E
    pairs and contains every lower pair of each (a total-degree set); offsets [I, 2].
    Returns [E, I, ...] with row (a, b) = sum_p w_p (x_p - ox)^a (y_p - oy)^b.
    Done as a shift along x then along y: one fused multiply-add on an [I, ...] row per term.
    """
    row = {e: r for r, e in enumerate(exponents)}
    top = max(max(e) for e in exponents)
    extra = (1,) * (moments.dim() - 2)
    shifted = moments
    for axis in (0, 1):
        neg = (-offsets[:, axis]).reshape(-1, *extra).to(moments.dtype)
        powers = [None, neg]
        for _ in range(2, top + 1):
            powers.append(powers[-1] * neg)
        out = torch.empty_like(shifted)
        for r, e in enumerate(exponents):
            terms = [(e[axis] - lower, (lower, e[1]) if axis == 0 else (e[0], lower), lower)
                     for lower in range(e[axis])]
            if not terms:
                out[r] = shifted[r]
                continue
            for i, (power, src, lower) in enumerate(terms):  # first term writes, the rest add
                base = shifted[r] if i == 0 else out[r]
                torch.addcmul(base, powers[power], shifted[row[src]], value=math.comb(e[axis], lower),
                              out=out[r])
        shifted = out
    return shifted


@dataclass
class ChunkDerivatives:
    """Per-chunk pieces of d I_pc / d features for the listed Gaussians of active tiles.

    active [Ta]; pos [Ta, K]; valid [Ta, K]; s [Ta, P, K, 3] = d I_pc / d exponent;
    w [Ta, P, K] compositing weights (d I_pc / d colour_c).
    """

    active: Tensor
    pos: Tensor
    valid: Tensor
    s: Tensor
    w: Tensor


class ViewWalk:
    """One view's tile walk with what the Fisher and the variance maps need."""

    def __init__(self, proj, width: int, height: int, background: Tensor, settings: RenderSettings):
        dtype, device = proj.means2d.dtype, proj.means2d.device
        ts = settings.tile_size
        self.width, self.height = width, height
        self.bins = bin_gaussians(proj.means2d, proj.radii, proj.depths, width, height, ts)
        psi = intersection_coeffs(self.bins, proj.means2d, proj.conics, proj.opacities)
        self.colors = proj.colors[self.bins.gauss_ids]  # [I, 3]
        self.phi = tile_monomials(ts, dtype, device)
        done = outside_image(self.bins, width, height, device)
        self.acc, self.final, self.records = composite_forward(psi, self.colors, self.bins, self.phi,
                                                               done, settings.chunk)
        self.mono, self.pair = _moment_tables(ts, dtype, device)
        self.offsets = local_means(self.bins, proj.means2d)  # [I, 2] mean2d - tile centre
        self.conics, self.opacities = proj.conics, proj.opacities
        self.behind_bg = self.final[..., None] * background.to(dtype)  # [T, P, 3]

    @property
    def basis(self) -> Tensor:
        """B [I, 6, 6] per intersection: h = B phi in tile-local coordinates."""
        g = self.bins.gauss_ids
        return _exponent_basis(self.conics[g], self.offsets, self.opacities[g])

    def chunks(self, tile_block: int = 64):
        """Yield ``ChunkDerivatives`` per depth chunk, in blocks of ``tile_block`` tiles so the
        [B, P, K, 3] temporaries of one block stay in cache (measured 1.1x at 200x200)."""
        for rec in self.records:
            for lo in range(0, rec.active.numel(), tile_block):
                part = slice(lo, lo + tile_block)
                yield self._derivatives(rec.active[part], rec.pos[part], rec.valid[part],
                                        rec.acc_before[part], rec.alpha[part], rec.t_excl[part],
                                        rec.live[part])

    def _derivatives(self, a, pos, valid, acc_before, alpha, t_excl, live) -> ChunkDerivatives:
        f = self.colors[pos]  # [Ta, K, 3]
        w = alpha * t_excl  # [Ta, P, K]
        wf = w[..., None] * f[:, None]  # [Ta, P, K, 3]
        behind = (self.acc[a] - acc_before + self.behind_bg[a])[:, :, None, :]
        # s_c = alpha (T f_c - suffix_c / (1 - alpha)) = w f_c - alpha / (1 - alpha) suffix_c, with
        # suffix = the colour composited behind each Gaussian = behind - cumsum(w f) (in place)
        minus_suffix = torch.cumsum(wf, dim=2).sub_(behind)
        odds = alpha / (1 - alpha)
        s = minus_suffix.mul_(odds[..., None]).add_(wf).mul_(live[..., None])  # 0 where clamped
        return ChunkDerivatives(a, pos, valid, s, w)


def _channel_sum_of_squares(s: Tensor) -> Tensor:
    """sum_c s_c^2 over the last axis (size 3), [...]; measured ~6x faster than
    ``s.square().sum(-1)`` on CPU, where reducing a size-3 innermost axis is slow."""
    c0, c1, c2 = s.unbind(-1)
    return torch.addcmul(torch.addcmul(c0 * c0, c1, c1), c2, c2)


def feature_fisher(walk: ViewWalk, channel_summed: bool) -> tuple[Tensor, Tensor]:
    """(seen [M], G [M, 9, 9] float64): the Gaussians the walk reached (sorted ids) and for each
    the sum over pixels and channels of d I / d features outer products (every other Gaussian
    has G = 0). ``channel_summed``: the outer products of the channel-summed derivative
    sum_c d I_c / d features instead (``fisherrf_released``).

    Per walked intersection (early termination leaves most listed ones unwalked), tile-local
    pixel moments are shifted to the Gaussian's mean (``centre_moments``), summed per Gaussian,
    and only then mapped to feature space with the Gaussian's own basis C (h = C psi(d)).
    """
    device, f64 = walk.phi.device, torch.float64
    m4, m2, w2, walked = [], [], [], []
    for ch in walk.chunks():
        keep = ch.valid.reshape(-1)
        s, w = ch.s, ch.w
        ta, pix, k = w.shape
        # left-multiplying by the small [15, P] / [6, P] tables keeps the big tensors in place
        weight = s.sum(-1).square() if channel_summed else _channel_sum_of_squares(s)
        sq = torch.matmul(walk.mono.T, weight)  # [Ta, 15, K]
        m4.append(sq.transpose(1, 2).reshape(-1, sq.shape[1])[keep])
        sw = torch.matmul(walk.phi.T, (s * w[..., None]).reshape(ta, pix, k * 3))  # [Ta, 6, K*3]
        m2.append(sw.reshape(ta, 6, k, 3).permute(0, 2, 1, 3).reshape(-1, 6, 3)[keep])
        w2.append(w.square().sum(1).reshape(-1)[keep])
        walked.append(ch.pos.reshape(-1)[keep])
    walked = torch.cat(walked)  # [W] positions into the intersection arrays
    seen, ids = torch.unique(walk.bins.gauss_ids[walked], return_inverse=True)
    n, offsets = seen.numel(), walk.offsets[walked].double()
    mu4 = centre_moments(torch.cat(m4).T.double(), offsets, MOMENT_EXPONENTS)  # [15, W]
    mu2 = centre_moments(torch.cat(m2).permute(1, 0, 2).double(), offsets, PHI_EXPONENTS)  # [6, W, 3]
    mu4_sum = torch.zeros(n, mu4.shape[0], dtype=f64, device=device).index_add_(0, ids, mu4.T)
    mu2_sum = torch.zeros(n, 6, 3, dtype=f64, device=device).index_add_(0, ids, mu2.transpose(0, 1))
    w2_sum = torch.zeros(n, dtype=f64, device=device).index_add_(0, ids, torch.cat(w2).double())
    basis = _centred_basis(walk.conics[seen].double(), walk.opacities[seen].double())  # [M, 6, 6]
    geometry = basis @ mu4_sum[:, walk.pair] @ basis.transpose(1, 2)
    return seen, assemble_feature_fisher(geometry, basis @ mu2_sum, w2_sum, channel_summed)


def assemble_feature_fisher(geometry: Tensor, cross: Tensor, w2: Tensor,
                            channel_summed: bool) -> Tensor:
    """G [M, 9, 9] from its blocks: geometry [M, 6, 6] (already of the chosen kind), the
    per-channel cross sums sum_p s_c w h [M, 6, 3] and sum_p w^2 [M]. Channel-summed: the
    derivative sum_c dI_c has cross sum_c' (s_c' w h) with every colour and colour block
    sum_p w^2 in every entry (each colour feature moves its own channel by w)."""
    n = geometry.shape[0]
    G = geometry.new_zeros(n, 9, 9)
    G[:, :6, :6] = geometry
    if channel_summed:
        cross = cross.sum(-1, keepdim=True).expand(n, 6, 3)
        G[:, 6:, 6:] = w2[:, None, None].expand(n, 3, 3)
    else:
        G[:, 6:, 6:] = torch.diag_embed(w2[:, None].expand(n, 3))
    G[:, :6, 6:] = cross
    G[:, 6:, :6] = cross.transpose(1, 2)
    return G


def variance_map(walk: ViewWalk, feature_cov: Tensor) -> Tensor:
    """Per-pixel predictive variance sum_i J_pc,i^2 S_i, [H, W, 3] (float64).

    feature_cov [N, 9, 9] = A diag(S) A^T per Gaussian, the posterior covariance pushed to the
    Gaussian's 2D features; per (pixel, Gaussian) the variance term is d^T C d with
    d = [s_c h ; w e_c], h = B phi, so h^T C h = phi^T (B^T C B) phi (moments of degree <= 4).
    """
    img = torch.zeros(walk.bins.num_tiles, walk.phi.shape[0], 3, dtype=torch.float64,
                      device=walk.phi.device)
    ids_all = walk.bins.gauss_ids
    cov = feature_cov[ids_all].to(walk.phi.dtype)  # [I, 9, 9]
    bt = walk.basis.transpose(-1, -2)
    quad = bt @ cov[:, :6, :6] @ walk.basis  # [I, 6, 6] on phi
    q15 = quad.new_zeros(quad.shape[0], walk.mono.shape[1])
    q15.index_add_(1, walk.pair.reshape(-1), quad.reshape(quad.shape[0], -1))
    lin = bt @ cov[:, :6, 6:]  # [I, 6, 3]
    col = torch.diagonal(cov[:, 6:, 6:], dim1=-2, dim2=-1)  # [I, 3]
    for ch in walk.chunks():
        pos = ch.pos
        hq = torch.einsum("pm,tkm->tpk", walk.mono, q15[pos])  # h^T C_geo h
        hl = torch.einsum("pj,tkjc->tpkc", walk.phi, lin[pos])  # h^T C_cross
        w = ch.w * ch.valid[:, None, :]
        term = ch.s ** 2 * hq[..., None] + 2 * ch.s * w[..., None] * hl \
            + (w * w)[..., None] * col[pos][:, None]
        img.index_add_(0, ch.active, term.sum(2).double())
    return untile(img, walk.bins, walk.width, walk.height)


# (a, b) pairs of the upper triangle of the 6x6 exponent block, in ``kernels.fisher_rows`` order
_UPPER = [(a, b) for a in range(6) for b in range(a, 6)]


def _compiled_fisher_rows(proj, width: int, height: int, background: Tensor, tile_size: int,
                          channel_summed: bool, workers: int):
    """The compiled walk of one view's projection: (row_ids [R], rows [R, 40] float64), one row
    of Fisher pixel sums per walked intersection (``kernels.fisher_rows``). The walk composites
    no feature channel: only its final transmittance and walked lengths are needed."""
    kernels = compiled.load()
    bins = compiled.CompiledBins(proj.means2d, proj.conics, proj.opacities, proj.radii,
                                 proj.depths, width, height, tile_size, workers)
    colors = compiled.to_numpy(proj.colors)
    _, final, walked = bins.forward(np.empty((colors.shape[0], 0), dtype=colors.dtype), workers)
    row_start, row_ids = bins.walked_rows(walked)
    rows = kernels.fisher_rows(bins.gauss_ids, bins.offsets, row_start, row_ids.shape[0],
                               bins.packed, colors, final, walked,
                               compiled.to_numpy(background.double()), bins.tiles_x, tile_size,
                               channel_summed, workers)
    return row_ids, rows


def feature_fisher_compiled(proj, width: int, height: int, background: Tensor,
                            tile_size: int, channel_summed: bool) -> tuple[Tensor, Tensor]:
    """``feature_fisher`` by the compiled walk: (seen [M], G [M, 9, 9] float64).

    The kernel sums, per walked intersection, S h h^T, s_c w h and w^2 at each pixel's own offset
    (no moment shifting); the rows are summed per Gaussian in a fixed order, then laid out as G.
    """
    row_ids, rows = _compiled_fisher_rows(proj, width, height, background, tile_size,
                                          channel_summed, compiled.use_threads())
    seen, ids = torch.unique(torch.from_numpy(row_ids), return_inverse=True)
    sums = torch.zeros(seen.numel(), rows.shape[1], dtype=torch.float64).index_add_(
        0, ids, torch.from_numpy(rows))
    geometry = sums.new_zeros(seen.numel(), 6, 6)
    a, b = zip(*_UPPER)
    geometry[:, a, b] = sums[:, :21]
    geometry[:, b, a] = sums[:, :21]
    G = assemble_feature_fisher(geometry, sums[:, 21:39].reshape(-1, 6, 3), sums[:, 39],
                                channel_summed)
    return seen.to(proj.means2d.device), G


@dataclass
class ViewFactors:
    """One view's Fisher factors for the M Gaussians its walk reached (all others have F = 0).

    seen [M] sorted Gaussian ids; jacobian: ``FeatureJacobian`` of those M Gaussians;
    feature_fisher [M, 9, 9] float64 (G); walk: the view's ``ViewWalk``; column_factor [M, P]:
    for ``fisherrf_released``, the activation derivatives applied once to the Fisher of the
    activated parameters (``jacobian`` is then w.r.t. those), else None.
    """

    seen: Tensor
    jacobian: FeatureJacobian
    feature_fisher: Tensor
    walk: ViewWalk
    column_factor: Tensor | None = None

    @property
    def width(self) -> int:
        """P, the Fisher's entries per Gaussian."""
        return sum(w for _, w in self.jacobian.layout)

    def fisher_diagonal(self, n: int) -> Tensor:
        """diag(A^T G A) for all n Gaussians, [N, P] float64 (times ``column_factor``)."""
        return self.write_fisher_diagonal(self.feature_fisher.new_zeros(n, self.width))

    def write_fisher_diagonal(self, out: Tensor) -> Tensor:
        """``fisher_diagonal`` written into ``out`` [N, P] float64 that holds zeros (the rows of
        Gaussians the walk did not reach stay zero); returns ``out``."""
        diag = self.jacobian.fisher_diagonal(self.feature_fisher)
        out[self.seen] = diag if self.column_factor is None else diag * self.column_factor
        return out

    def feature_covariance(self, posterior_var: Tensor) -> Tensor:
        """A diag(S) A^T [N, 9, 9] float64 for S [N, P] (zero for Gaussians not reached)."""
        A = self.jacobian.dense().double()
        cov = self.feature_fisher.new_zeros(posterior_var.shape[0], 9, 9)
        cov[self.seen] = torch.einsum("nip,np,njp->nij", A, posterior_var[self.seen].double(), A)
        return cov


def activated_once(jac: FeatureJacobian, log_scales: Tensor) -> tuple[FeatureJacobian, Tensor]:
    """FisherRF's activation rule: (the Jacobian w.r.t. scale = exp(log-scale) and opacity =
    sigmoid(logit) instead of the raw parameters, the factor [M, P] each Fisher column is then
    multiplied by once: the scale for log-scales, sigmoid' for the opacity, 1 elsewhere).

    log_scales [M, 3] of the Jacobian's M Gaussians."""
    geometry, slope = jac.geometry.clone(), jac.opacity_slope
    factor = geometry.new_ones(geometry.shape[0], sum(w for _, w in jac.layout), dtype=torch.float64)
    for group, cols, geo_cols in jac.column_blocks():
        if group == "log_scales":
            scales = log_scales.exp().to(geometry.dtype)
            geometry[:, :, geo_cols] = geometry[:, :, geo_cols] / scales[:, None, :]
            factor[:, cols] = scales.double()
        elif group == "logit_opacities":
            factor[:, cols] = slope.double()[:, None]
    return replace(jac, geometry=geometry, opacity_slope=torch.ones_like(slope)), factor


@dataclass(frozen=True)
class FisherBackend:
    """The Fisher's twins resolved for one backend name (``splat.backend`` lists them):
    ``project`` -> Projection; ``walk(proj, width, height, background, settings, channel_summed)``
    -> (seen [M], G [M, 9, 9], the torch ``ViewWalk`` or None); ``jacobian`` -> FeatureJacobian."""

    name: str
    project: object
    walk: object
    jacobian: object


def _compiled_walk(proj, width, height, background, settings, channel_summed):
    seen, G = feature_fisher_compiled(proj, width, height, background, settings.tile_size,
                                      channel_summed)
    return seen, G, None


def _torch_walk(proj, width, height, background, settings, channel_summed):
    walk = ViewWalk(proj, width, height, background, settings)
    seen, G = feature_fisher(walk, channel_summed)
    return seen, G, walk


def fisher_backend(settings: RenderSettings, device: torch.device) -> FisherBackend:
    """The compiled walk when ``settings.backend`` resolves to ``compiled``, else the torch tile
    walk (``tiles``; the dense and loop oracles have no Fisher walk of their own)."""
    if compiled.resolve_backend(settings.backend, device) == "compiled":
        return FisherBackend("compiled", compiled.project_compiled, _compiled_walk,
                             feature_jacobian_compiled)
    return FisherBackend("tiles", project, _torch_walk, feature_jacobian)


def view_factors(gaussians: Gaussians, cameras: Cameras, background: Tensor | None = None,
                 spec: "FisherSpec" = None, settings: RenderSettings = RenderSettings()):
    """Yield one ``ViewFactors`` per camera: walk first, then the Jacobian of only the Gaussians
    the walk reached (occluded and off-screen ones have zero Fisher); ``fisher_backend`` picks
    the compiled or the torch twins."""
    spec = spec or FisherSpec()
    if len(gaussians) == 0:
        raise ValueError("gaussians: cannot compute the Fisher of an empty scene")
    gaussians.validate()
    backend = fisher_backend(settings, gaussians.means.device)
    cams = cameras.to(device=gaussians.means.device, dtype=gaussians.means.dtype)
    bg = gaussians.means.new_zeros(3) if background is None else background
    for i in range(len(cams)):
        view = (cams.viewmats[i], cams.Ks[i], cams.width, cams.height)
        with torch.no_grad():
            proj = backend.project(gaussians.detach(), *view, spec.sh_degree, settings.near)
        seen, G, walk = backend.walk(proj, cams.width, cams.height, bg, settings, spec.channel_summed)
        jac = backend.jacobian(gaussians.index(seen), *view, spec.groups, spec.sh_degree, settings.near)
        if spec.channel_summed:
            jac, factor = activated_once(jac, gaussians.log_scales[seen])
            yield ViewFactors(seen, jac, G, walk, factor)
        else:
            yield ViewFactors(seen, jac, G, walk)


def view_fisher(gaussians: Gaussians, cameras: Cameras, background: Tensor | None = None,
                spec: FisherSpec = FisherSpec(),
                settings: RenderSettings = RenderSettings()) -> Tensor:
    """Exact diagonal Fisher of each view's RGB image: [C, N, P] float64.

    P = the selected raw parameters per Gaussian in ``param_layout`` order. Gaussians that no
    pixel sees get exactly zero.
    """
    if len(cameras) == 0:
        raise ValueError("view_fisher: no cameras (the Fisher of no view is not defined here)")
    if fused_fisher_available(gaussians, settings):
        return view_fisher_fused(gaussians, cameras, background, spec, settings)
    out = None
    for c, factors in enumerate(view_factors(gaussians, cameras, background, spec, settings)):
        if out is None:  # one [C, N, P] block, each view written in place (no per-view copy)
            out = factors.feature_fisher.new_zeros(len(cameras), len(gaussians), factors.width)
        factors.write_fisher_diagonal(out[c])
    return out


@dataclass
class SparseFisher:
    """One view's exact diagonal Fisher in compact form: ids [M] (sorted Gaussian ids, int64) of
    the Gaussians its walk reached and their rows [M, P] float64; every other row is zero."""

    ids: Tensor
    rows: Tensor

    def dense(self, n: int) -> Tensor:
        """[N, P] float64."""
        out = self.rows.new_zeros(n, self.rows.shape[1])
        out[self.ids] = self.rows
        return out


def _fused_views(gaussians: Gaussians, cameras: Cameras, background: Tensor | None,
                 spec: FisherSpec, settings: RenderSettings):
    """Yield one ``SparseFisher`` per camera by the fused compiled path (``diagonal_kernels``):
    the projection of the visible Gaussians, the forward and Fisher walks tile by tile in one
    kernel (``kernels.walk_fisher``: the Fisher rows of ``feature_fisher_compiled`` without
    recomputing each pair), the rows summed per Gaussian, then diag(A^T G A) of the reached
    Gaussians written by one kernel. Several cameras are computed
    side by side, one per thread (``compiled.map_in_threads``); one camera splits its kernels over
    the threads instead. Either way each view's numbers are the same."""
    from pipeline.fisher import diagonal_kernels
    if len(gaussians) == 0:
        raise ValueError("gaussians: cannot compute the Fisher of an empty scene")
    gaussians.validate()
    kernels = compiled.load()
    layout = param_layout(gaussians, spec.groups)
    width = sum(w for _, w in layout)
    groups = np.array([any(g == name for g, _ in layout) for name in PARAM_GROUPS])
    cams = cameras.to(device=gaussians.means.device, dtype=gaussians.means.dtype)
    bg = gaussians.means.new_zeros(3) if background is None else background
    g = gaussians.detach()
    n, degree = len(g), active_sh_degree(g, spec.sh_degree)
    arrays = [compiled.to_numpy(v) for v in g.params().values()]
    background = compiled.to_numpy(bg.double())

    def one_view(c: int) -> SparseFisher:
        kernel_workers = compiled.use_threads()  # 1 when views run side by side
        proj = compiled.project_visible(arrays, cams.viewmats[c], cams.Ks[c], cams.width,
                                        cams.height, degree, settings.near, kernel_workers)
        bins = compiled.CompiledBins(proj.means2d, proj.conics, proj.opacities, proj.radii,
                                     proj.depths, cams.width, cams.height, settings.tile_size,
                                     kernel_workers)
        longest, rows = kernels.walk_fisher(bins.gauss_ids, bins.offsets, bins.counts, bins.packed,
                                            compiled.to_numpy(proj.colors), background, cams.width,
                                            cams.height, bins.tiles_x, settings.tile_size,
                                            spec.channel_summed, kernel_workers)
        ids, sums = kernels.sum_walked_rows(bins.gauss_ids, bins.offsets, longest, rows, n)
        out = np.empty((ids.shape[0], width))
        diagonal_kernels.fisher_diagonal(
            ids, sums, *arrays, compiled.to_numpy(cams.viewmats[c].double()),
            compiled.intrinsics(cams.Ks[c]),
            int(cams.width), int(cams.height), int(degree), float(settings.near), groups,
            spec.channel_summed, out, kernel_workers)
        return SparseFisher(torch.from_numpy(ids), torch.from_numpy(out))

    yield from compiled.map_in_threads(one_view, len(cams), compiled.use_threads())


def fused_fisher_available(gaussians: Gaussians, settings: RenderSettings) -> bool:
    """Whether ``settings`` resolve to the compiled backend with its fused paths on."""
    return (fisher_backend(settings, gaussians.means.device).name == "compiled"
            and compiled.fused_enabled())


def view_fisher_fused(gaussians: Gaussians, cameras: Cameras, background: Tensor | None = None,
                      spec: FisherSpec = FisherSpec(),
                      settings: RenderSettings = RenderSettings()) -> Tensor:
    """``view_fisher`` on the compiled backend with its tail fused: [C, N, P] float64."""
    out = None
    for c, view in enumerate(_fused_views(gaussians, cameras, background, spec, settings)):
        if out is None:
            out = torch.zeros(len(cameras), len(gaussians), view.rows.shape[1], dtype=torch.float64)
        out[c, view.ids] = view.rows
    return out


def view_fisher_sparse(gaussians: Gaussians, cameras: Cameras, background: Tensor | None = None,
                       spec: FisherSpec = FisherSpec(),
                       settings: RenderSettings = RenderSettings()) -> list[SparseFisher]:
    """``view_fisher`` as one ``SparseFisher`` per view (no [C, N, P] block: a pool of hundreds
    of views at 10k Gaussians was a 1.2 GB allocation per round). The fused compiled path when
    ``settings`` resolve to it, else each view's dense Fisher compacted to its non-zero rows."""
    if len(cameras) == 0:
        raise ValueError("view_fisher: no cameras (the Fisher of no view is not defined here)")
    if fused_fisher_available(gaussians, settings):
        return list(_fused_views(gaussians, cameras, background, spec, settings))
    views = []
    for c in range(len(cameras)):
        dense = view_fisher(gaussians, cameras[c:c + 1], background, spec, settings)[0]
        ids = torch.nonzero(dense.abs().sum(1) > 0).flatten()
        views.append(SparseFisher(ids, dense[ids]))
    return views


def predictive_variance_maps(gaussians: Gaussians, cameras: Cameras, posterior_var: Tensor,
                             background: Tensor | None = None, spec: FisherSpec = FisherSpec(),
                             settings: RenderSettings = RenderSettings()) -> Tensor:
    """Per-pixel predictive variance maps [C, H, W, 3] for a diagonal posterior S [N, P].

    Computed on the torch tile walk (``variance_map`` needs its chunk records).
    """
    tiles = replace(settings, backend="tiles")
    return torch.stack([variance_map(f.walk, f.feature_covariance(posterior_var)) for f in
                        view_factors(gaussians, cameras, background, spec, tiles)])
