"""Tile-binned, depth-sorted, front-to-back alpha compositing (the fast path).

Layout (see shared design notes): the image is cut into ``tile_size`` x ``tile_size`` tiles; each
Gaussian is listed in every tile its 3-sigma square [u - r, u + r] x [v - r, v + r] touches;
each tile's list is sorted by depth. All tiles are then walked together in depth chunks of
``chunk`` Gaussians, gathering per (tile, Gaussian) rather than per (pixel, Gaussian), carrying
the transmittance between chunks, and dropping a tile once all its pixels have terminated.

Compositing rules (3DGS): alpha = min(0.99, opacity * exp(power)), power = -1/2 d^T conic d;
Gaussians with alpha < 1/255 are skipped (3DGS also skips power > 0, which cannot happen here:
conics are positive definite by construction, EPS_2D dilation included); a pixel stops before the Gaussian that
would bring its transmittance below 1e-4 (that Gaussian is not composited).
Differentiable by autograd with respect to means2d, conics, opacities and features.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

# The public surface: the compositor and its sparse weights, and the tile walk's building blocks
# that the exact Fisher (``fisher.exact``) walks with the same rules (bins, monomials, per-
# intersection coefficients, the forward walk, untiling).
__all__ = ["ALPHA_MAX", "ALPHA_MIN", "T_MIN", "TileBins", "ChunkRecord", "CompositingWeights",
           "square_tile_rects", "depth_ranks", "bin_gaussians", "tile_monomials", "local_means",
           "intersection_coeffs", "composite_forward", "untile", "outside_image", "rasterize",
           "compositing_weights"]

ALPHA_MAX = 0.99
ALPHA_MIN = 1.0 / 255.0
T_MIN = 1e-4


@dataclass
class TileBins:
    """Per-tile depth-sorted Gaussian lists.

    gauss_ids [I]: Gaussian index per (tile, Gaussian) intersection, sorted by tile then depth;
    offsets [T], counts [T]: where each tile's list starts in ``gauss_ids`` and its length.
    """

    gauss_ids: Tensor
    offsets: Tensor
    counts: Tensor
    tiles_x: int
    tiles_y: int
    tile_size: int

    @property
    def num_tiles(self) -> int:
        return self.tiles_x * self.tiles_y


def square_tile_rects(means2d: Tensor, radii: Tensor, tiles_x: int, tiles_y: int, tile_size: int):
    """Half-open tile ranges [x0, x1) x [y0, y1) touched by each Gaussian's square; [N] each.

    A Gaussian with radius 0 (culled) gets an empty range.
    """
    u, v = means2d.detach().unbind(-1)
    r = radii.to(u.dtype)
    live = radii > 0
    x0 = torch.floor((u - r) / tile_size).clamp(0, tiles_x).long()
    x1 = (torch.floor((u + r) / tile_size) + 1).clamp(0, tiles_x).long()
    y0 = torch.floor((v - r) / tile_size).clamp(0, tiles_y).long()
    y1 = (torch.floor((v + r) / tile_size) + 1).clamp(0, tiles_y).long()
    x1 = torch.where(live, x1, x0)
    y1 = torch.where(live, y1, y0)
    return x0, x1, y0, y1


def depth_ranks(depths: Tensor) -> Tensor:
    """Rank of each Gaussian in a stable front-to-back order, [N] int64 (ties: lower index first)."""
    order = torch.argsort(depths.detach(), stable=True)
    ranks = torch.empty_like(order)
    ranks[order] = torch.arange(order.numel(), device=order.device)
    return ranks


@torch.no_grad()
def bin_gaussians(means2d: Tensor, radii: Tensor, depths: Tensor, width: int, height: int,
                  tile_size: int = 8) -> TileBins:
    """Build depth-sorted per-tile lists, fully vectorised (one argsort on tile * N + depth rank)."""
    n = means2d.shape[0]
    device = means2d.device
    tiles_x, tiles_y = -(-width // tile_size), -(-height // tile_size)
    x0, x1, y0, y1 = square_tile_rects(means2d, radii, tiles_x, tiles_y, tile_size)
    nx, ny = (x1 - x0).clamp(min=0), (y1 - y0).clamp(min=0)
    per_gauss = nx * ny  # [N]
    gid = torch.repeat_interleave(torch.arange(n, device=device), per_gauss)  # [I]
    starts = torch.cumsum(per_gauss, 0) - per_gauss
    local = torch.arange(gid.numel(), device=device) - starts[gid]
    tile = (y0[gid] + local // nx[gid]) * tiles_x + x0[gid] + local % nx[gid]
    key = tile * max(n, 1) + depth_ranks(depths)[gid]
    order = torch.argsort(key)
    gauss_ids = gid[order]
    counts = torch.bincount(tile, minlength=tiles_x * tiles_y)
    offsets = torch.cumsum(counts, 0) - counts
    return TileBins(gauss_ids, offsets, counts, tiles_x, tiles_y, tile_size)


def tile_monomials(tile_size: int, dtype, device) -> Tensor:
    """phi [P, 6] = (x^2, xy, y^2, x, y, 1) at pixel centres in tile-local coordinates.

    Coordinates are relative to the tile centre, so |x|, |y| <= tile_size / 2 and the quadratic
    expansion below stays well conditioned in float32.
    """
    k = torch.arange(tile_size * tile_size, device=device)
    x = (k % tile_size).to(dtype) + 0.5 - tile_size / 2
    y = (k // tile_size).to(dtype) + 0.5 - tile_size / 2
    return torch.stack([x * x, x * y, y * y, x, y, torch.ones_like(x)], dim=-1)


def local_means(bins: TileBins, means2d: Tensor) -> Tensor:
    """[I, 2] each intersection's Gaussian mean relative to its tile's centre (pixels)."""
    ts = bins.tile_size
    tile = torch.repeat_interleave(torch.arange(bins.num_tiles, device=means2d.device), bins.counts)
    centre = torch.stack([(tile % bins.tiles_x) * ts + ts / 2, (tile // bins.tiles_x) * ts + ts / 2], -1)
    return means2d[bins.gauss_ids] - centre.to(means2d.dtype)


def intersection_coeffs(bins: TileBins, means2d: Tensor, conics: Tensor,
                        opacities: Tensor) -> Tensor:
    """Exponent coefficients per (tile, Gaussian) intersection, so that for every pixel of the tile
    ``log(opacity) - 1/2 d^T Q d = phi(pixel) . psi``. Returns psi [I, 6].

    Differentiable (autograd) w.r.t. means2d [N, 2], conics [N, 3], opacities [N].
    """
    g = bins.gauss_ids
    mx, my = local_means(bins, means2d).unbind(-1)
    a, b, c = conics[g].unbind(-1)
    log_o = torch.log(opacities[g].clamp_min(torch.finfo(opacities.dtype).tiny))  # opacity 0: no NaN grad
    psi = torch.stack([-0.5 * a, -b, -0.5 * c, a * mx + b * my, b * mx + c * my,
                       log_o - 0.5 * (a * mx * mx + c * my * my) - b * mx * my], dim=-1)
    return psi


def _chunk_state(phi: Tensor, psi: Tensor, trans: Tensor) -> dict:
    """Alpha and transmittance of one depth chunk for the active tiles.

    phi [P, 6]; psi [Ta, 6, K] (padding entries have a -inf constant term); trans [Ta, P] before
    the chunk, 0 for pixels that already terminated. Returns alpha, t_excl, weights
    (all [Ta, P, K]), live [Ta, P, K] (composited and unclamped: d alpha / d exponent = alpha),
    trans_after [Ta, P] and ends [Ta, P] (pixels that terminate inside this chunk).
    """
    alpha = torch.exp(torch.matmul(phi, psi))  # [Ta, P, K]
    live = (alpha >= ALPHA_MIN) & (alpha < ALPHA_MAX)
    alpha.masked_fill_(alpha < ALPHA_MIN, 0.0).clamp_(max=ALPHA_MAX)
    one_minus = 1 - alpha
    cum = torch.cumprod(one_minus, dim=-1)
    trans_after = trans * cum[..., -1]
    ends = (trans_after < T_MIN) & (trans > 0)
    if bool(ends.any()):  # only those pixel rows need the termination rule
        ti, pi = torch.nonzero(ends, as_tuple=True)
        stop = trans[ti, pi, None] * cum[ti, pi] < T_MIN  # [R, K], a suffix per row
        alpha_r = alpha[ti, pi].masked_fill(stop, 0.0)
        alpha[ti, pi] = alpha_r
        one_minus[ti, pi] = 1 - alpha_r
        cum[ti, pi] = torch.cumprod(1 - alpha_r, dim=-1)
        live[ti, pi] = live[ti, pi] & ~stop
        trans_after = trans * cum[..., -1]
    t_excl = cum / one_minus * trans.unsqueeze(-1)  # one_minus >= 0.01
    live &= t_excl > 0
    return {"alpha": alpha, "t_excl": t_excl, "weights": alpha * t_excl,
            "live": live, "trans_after": trans_after, "ends": ends}


def _walk(bins: TileBins, done: Tensor, chunk: int):
    """Yield per chunk (active tiles [Ta], positions [Ta, K], valid [Ta, K]); the caller updates
    ``done`` [T, P] in place between steps so finished tiles drop out."""
    steps = torch.arange(chunk, device=done.device)
    last = max(bins.gauss_ids.numel() - 1, 0)
    active = torch.nonzero(bins.counts > 0)[:, 0]
    start = 0
    while active.numel() > 0:
        valid = (start + steps)[None, :] < bins.counts[active, None]
        pos = (bins.offsets[active, None] + start + steps).clamp(max=last)
        yield active, pos, valid
        start += chunk
        more = (~done[active].all(dim=1)) & (bins.counts[active] > start)
        active = active[more]


def _chunk_psi(psi: Tensor, pos: Tensor, valid: Tensor) -> Tensor:
    """Gathered coefficients [Ta, 6, K]; padding entries get exponent -inf (alpha 0)."""
    g = psi[pos]  # [Ta, K, 6]
    g[..., 5].masked_fill_(~valid, float("-inf"))
    return g.transpose(1, 2)


@dataclass
class ChunkRecord:
    """What the forward walk keeps of one depth chunk (Ta active tiles, K listed Gaussians).

    active [Ta] tile ids; pos [Ta, K] positions into the intersection arrays; valid [Ta, K];
    acc_before [Ta, P, D]; alpha, t_excl [Ta, P, K]; live [Ta, P, K] (d alpha / d exponent = alpha).
    """

    active: Tensor
    pos: Tensor
    valid: Tensor
    acc_before: Tensor
    alpha: Tensor
    t_excl: Tensor
    live: Tensor


@torch.no_grad()
def composite_forward(psi: Tensor, feats: Tensor, bins: TileBins, phi: Tensor, done: Tensor,
                      chunk: int) -> tuple[Tensor, Tensor, list[ChunkRecord]]:
    """The tile walk: accumulated features [T, P, D], final transmittance [T, P], chunk records.

    psi [I, 6] and feats [I, D] per intersection; done [T, P] marks pixels outside the image and
    is updated in place.
    """
    num_tiles, pix = done.shape
    trans = psi.new_ones(num_tiles, pix).masked_fill_(done, 0.0)
    final = psi.new_ones(num_tiles, pix)
    acc = psi.new_zeros(num_tiles, pix, feats.shape[1])
    records = []
    for active, pos, valid in _walk(bins, done, chunk):
        acc_b = acc[active]
        st = _chunk_state(phi, _chunk_psi(psi, pos, valid), trans[active])
        acc[active] = acc_b + torch.bmm(st["weights"], feats[pos])
        ends = st["ends"]
        final[active] = torch.where(ends, st["trans_after"], final[active])
        trans[active] = st["trans_after"].masked_fill(ends, 0.0)
        done[active] = done[active] | ends
        records.append(ChunkRecord(active, pos, valid, acc_b, st["alpha"], st["t_excl"], st["live"]))
    return acc, torch.where(done, final, trans), records


class _TileComposite(torch.autograd.Function):
    """Front-to-back compositing over tiles with an analytic backward.

    Forward keeps, per chunk, the alphas, transmittances and live mask ([Ta, P, K] each; about
    9 bytes per (pixel, listed Gaussian) walked) and the features accumulated before the chunk.
    For an included Gaussian k of a pixel, with q_k = dL/dacc . f_k:
        dL/dalpha_k = T_k q_k - (sum_{i>k} w_i q_i + dL/dT_final T_final) / (1 - alpha_k).
    A terminated pixel carries T = 0 in the walk; its final transmittance is kept aside.
    """

    @staticmethod
    def forward(ctx, psi, feats, bins, phi, done, chunk):
        acc, final, records = composite_forward(psi, feats, bins, phi, done, chunk)
        ctx.records = records
        ctx.save_for_backward(psi, feats, phi, acc, final)
        return acc, final

    @staticmethod
    def backward(ctx, grad_acc, grad_trans):
        psi, feats, phi, acc, final = ctx.saved_tensors
        grad_psi, grad_feats = torch.zeros_like(psi), torch.zeros_like(feats)
        for rec in ctx.records:
            active, pos, valid, acc_b = rec.active, rec.pos, rec.valid, rec.acc_before
            alpha, t_excl, live = rec.alpha, rec.t_excl, rec.live
            f = feats[pos]  # [Ta, K, D]
            g_acc = grad_acc[active]  # [Ta, P, D]
            weights = alpha * t_excl
            q = torch.bmm(g_acc, f.transpose(1, 2))  # [Ta, P, K]
            behind = ((g_acc * (acc[active] - acc_b)).sum(-1)
                      + grad_trans[active] * final[active]).unsqueeze(-1)  # [Ta, P, 1]
            suffix = behind - torch.cumsum(weights * q, dim=-1)  # sum over i > k
            d_z = (t_excl * q - suffix / (1 - alpha)) * alpha
            d_z.masked_fill_(~live, 0.0)
            d_psi = torch.matmul(phi.T, d_z)  # [Ta, 6, K]
            d_f = torch.bmm(weights.transpose(1, 2), g_acc)  # [Ta, K, D]
            keep = valid.reshape(-1)
            flat = pos.reshape(-1)[keep]
            grad_psi.index_add_(0, flat, d_psi.transpose(1, 2).reshape(-1, 6)[keep])
            grad_feats.index_add_(0, flat, d_f.reshape(-1, f.shape[-1])[keep])
        return grad_psi, grad_feats, None, None, None, None


def untile(values: Tensor, bins: TileBins, width: int, height: int) -> Tensor:
    """[T, P, ...] per-tile pixel values -> [H, W, ...] image."""
    ts = bins.tile_size
    rest = values.shape[2:]
    img = values.reshape(bins.tiles_y, bins.tiles_x, ts, ts, *rest).transpose(1, 2)
    return img.reshape(bins.tiles_y * ts, bins.tiles_x * ts, *rest)[:height, :width]


def outside_image(bins: TileBins, width: int, height: int, device) -> Tensor:
    """[T, P] True for pixels of edge tiles that fall outside the image."""
    ts = bins.tile_size
    t = torch.arange(bins.num_tiles, device=device)
    k = torch.arange(ts * ts, device=device)
    col = (t % bins.tiles_x)[:, None] * ts + (k % ts)[None, :]
    row = (t // bins.tiles_x)[:, None] * ts + (k // ts)[None, :]
    return (col >= width) | (row >= height)


def rasterize(means2d: Tensor, conics: Tensor, opacities: Tensor, features: Tensor, radii: Tensor,
              depths: Tensor, width: int, height: int, tile_size: int = 8,
              chunk: int = 64) -> tuple[Tensor, Tensor]:
    """Composite N projected Gaussians into an image.

    means2d [N, 2], conics [N, 3], opacities [N], features [N, D] (colour, depth, ...),
    radii [N] int (0 = culled), depths [N]. Returns (features image [H, W, D], alpha [H, W]).
    No background is added: the caller adds (1 - alpha) * background.
    """
    bins = bin_gaussians(means2d, radii, depths, width, height, tile_size)
    psi = intersection_coeffs(bins, means2d, conics, opacities)
    feats = features[bins.gauss_ids]  # [I, D]
    phi = tile_monomials(tile_size, means2d.dtype, means2d.device)
    done = outside_image(bins, width, height, means2d.device)
    acc, trans = _TileComposite.apply(psi, feats, bins, phi, done, chunk)
    return untile(acc, bins, width, height), untile(1 - trans, bins, width, height)


@dataclass
class CompositingWeights:
    """Every nonzero compositing weight w = alpha T of one image, as a sparse list of E entries:
    pixel [E] (row-major index y * width + x), gaussian [E] (index into the N Gaussians), weight [E].
    A pixel's rendered feature is sum over its entries of weight * feature[gaussian]."""

    pixel: Tensor
    gaussian: Tensor
    weight: Tensor
    width: int
    height: int

    def composite(self, values: Tensor, power: int = 1) -> Tensor:
        """sum_g w_pg^power values_g for per-Gaussian ``values`` [N] -> [H, W] (differentiable in
        ``values``); power 1 is the ordinary composite, 2 ActiveNeRF's variance composite."""
        return self.per_pixel(self.weight.to(values.dtype) ** power * values[self.gaussian])

    def per_pixel(self, entries: Tensor) -> Tensor:
        """Sum per-entry values [E] over each pixel's entries -> [H, W]."""
        out = entries.new_zeros(self.width * self.height).index_add(0, self.pixel, entries)
        return out.reshape(self.height, self.width)


@torch.no_grad()
def compositing_weights(means2d: Tensor, conics: Tensor, opacities: Tensor, radii: Tensor,
                        depths: Tensor, width: int, height: int, tile_size: int = 8,
                        chunk: int = 64) -> CompositingWeights:
    """The compositing weights of the tile walk (same alphas, clamps and termination as
    ``rasterize``), listed per (pixel, Gaussian): means2d [N, 2], conics [N, 3], opacities [N],
    radii [N], depths [N]. For statistics that need w itself, not only sum_g w_pg f_g (e.g. the
    squared weights of ActiveNeRF's rendered variance)."""
    bins = bin_gaussians(means2d, radii, depths, width, height, tile_size)
    psi = intersection_coeffs(bins, means2d, conics, opacities)
    phi = tile_monomials(tile_size, means2d.dtype, means2d.device)
    done = outside_image(bins, width, height, means2d.device)
    # the compositor's own forward walk, with no features: its chunk records hold alpha and T
    _, _, records = composite_forward(psi, psi.new_zeros(psi.shape[0], 0), bins, phi, done, chunk)
    ts = tile_size
    pixels, gaussians, weights = [], [], []
    for rec in records:
        w = rec.alpha * rec.t_excl  # [Ta, P, K]
        ti, pi, ki = torch.nonzero((w > 0) & rec.valid[:, None, :], as_tuple=True)
        tile = rec.active[ti]
        pixels.append(((tile // bins.tiles_x) * ts + pi // ts) * width + (tile % bins.tiles_x) * ts + pi % ts)
        gaussians.append(bins.gauss_ids[rec.pos[ti, ki]])
        weights.append(w[ti, pi, ki])
    if not pixels:
        empty = means2d.new_zeros(0, dtype=torch.long)
        return CompositingWeights(empty, empty.clone(), means2d.new_zeros(0), width, height)
    return CompositingWeights(torch.cat(pixels), torch.cat(gaussians), torch.cat(weights), width, height)
