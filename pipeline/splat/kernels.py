"""Compiled CPU kernels (numba) for tile binning, compositing and the per-view Fisher walk.

NumPy arrays in, NumPy arrays out (``compiled.py`` wraps them as a torch backend); the 3DGS
constants come from ``rasterize.py``, the torch path.
The rules are those of ``rasterize.py`` and the 3DGS CUDA rasterizer, evaluated per pixel:
    power = -1/2 d^T Q d with d = pixel centre - mean2d, Q = [[a, b], [b, c]];
    alpha = min(ALPHA_MAX, opacity exp(power)); skipped when power > 0 or alpha < ALPHA_MIN;
    a pixel stops before the Gaussian that would take its transmittance below T_MIN.
The offset d is computed directly (not through a tile-centred quadratic expansion), so float32
keeps full precision however far a Gaussian's mean lies from the tile. Arithmetic is float64.

Layout: per-Gaussian values are packed in one row, ``packed [N, 8]`` = (u, v, a, b, c, opacity,
log(ALPHA_MIN / opacity), 0), so a pair costs one cache line; a pair whose power is clearly below
that log threshold is skipped without an ``exp``. Work is split over ``workers`` by interleaving
tiles (worker k takes tiles k, k + workers, ...): static, cheap, and balanced because neighbouring
tiles cost about the same. (numba's dynamic ``parallel_chunksize`` was measured 2-7x slower here.)

Backward and Fisher write per-intersection rows, and only for the walked prefix of each tile's
list (``walked_rows``): every row belongs to one tile, so there are no races and the per-Gaussian
sum (done by the caller in a fixed order) is deterministic whatever the thread schedule.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from pipeline.splat.rasterize import ALPHA_MAX, ALPHA_MIN, T_MIN  # the rules have one source

# prange loops only: numba would otherwise turn np.zeros & co. into parallel regions too, and a
# job given one thread must never start the thread pool (its idle threads spin on a busy core)
PRANGE_ONLY = {"prange": True, "comprehension": False, "reduction": False, "inplace_binop": False,
               "setitem": False, "numpy": False, "stencil": False, "fusion": False}

SKIP_MARGIN = 1e-6  # a pair is skipped without exp only when clearly below the alpha threshold
PACKED = 10
FISHER_ROW = 40  # 21 (S h h^T, upper triangle) + 18 (s_c w h) + 1 (w^2)


@njit(cache=True, inline="always")
def _pack_row(means2d, conics, opacities, g, out):
    """Gaussian g's packed row (``pack``) into out [PACKED]."""
    out[0], out[1] = means2d[g, 0], means2d[g, 1]
    a, b, c = float(conics[g, 0]), float(conics[g, 1]), float(conics[g, 2])
    out[2], out[3], out[4] = a, b, c
    o = float(opacities[g])
    out[5] = o
    out[6] = math.log(ALPHA_MIN / o) if o > 0.0 else np.inf
    k2 = 2.0 * (SKIP_MARGIN - out[6])
    det = a * c - b * b
    if not k2 > 0.0:
        out[7] = out[8] = -1.0
    elif det > 0.0 and a > 0.0 and c > 0.0 and k2 < np.inf:
        out[7] = math.sqrt(k2 * c / det) * (1.0 + 1e-6) + 1e-3
        out[8] = math.sqrt(k2 * a / det) * (1.0 + 1e-6) + 1e-3
    else:
        out[7] = out[8] = np.inf
    out[9] = 0.0


@njit(cache=True, nogil=True)
def pack(means2d, conics, opacities):
    """[N, 10] float64 rows (u, v, a, b, c, opacity, log(ALPHA_MIN / opacity), ex, ey, 0).

    (ex, ey): half-widths in pixels of the box around (u, v) outside which ``_pair`` skips every
    pixel by its threshold test (power < log(ALPHA_MIN / opacity) - SKIP_MARGIN, i.e.
    d^T Q d > k^2 = 2 (SKIP_MARGIN - log(ALPHA_MIN / opacity))): the ellipse's bounding box
    k sqrt(Sigma_xx), k sqrt(Sigma_yy) (Sigma = Q^-1), widened by a hair for rounding; negative
    when no pixel can pass (k^2 <= 0), inf when the conic is not positive definite (no box)."""
    n = means2d.shape[0]
    packed = np.empty((n, PACKED), dtype=np.float64)
    for g in range(n):
        _pack_row(means2d, conics, opacities, g, packed[g])
    return packed


@njit(parallel=PRANGE_ONLY, cache=True, nogil=True)
def pack_rects(means2d, conics, opacities, radii, tiles_x, tiles_y, tile_size, workers):
    """``pack`` and ``alpha_tile_rects`` in one pass over the Gaussians, on ``workers`` threads
    (contiguous blocks), for the Gaussians with radius > 0 only: a culled one's rect is empty (as
    ``alpha_tile_rects`` makes it) and its packed row is zeros, which nothing reads (no tile lists
    it). At 64 px most of a real scene's Gaussians are culled in any one view.
    Returns (packed [N, PACKED], rects [N, 4])."""
    n = means2d.shape[0]
    packed = np.zeros((n, PACKED), dtype=np.float64)
    rects = np.zeros((n, 4), dtype=np.int64)
    if workers == 1:  # no parallel region: no idle pool threads spinning beside the job
        _pack_rects_block(0, n, means2d, conics, opacities, radii, tiles_x, tiles_y, tile_size,
                          packed, rects)
    else:
        for w in prange(workers):
            _pack_rects_block(w * n // workers, (w + 1) * n // workers, means2d, conics,
                              opacities, radii, tiles_x, tiles_y, tile_size, packed, rects)
    return packed, rects


@njit(cache=True, nogil=True)
def _pack_rects_block(lo, hi, means2d, conics, opacities, radii, tiles_x, tiles_y, tile_size,
                      packed, rects):
    for g in range(lo, hi):
        if radii[g] > 0:
            _pack_row(means2d, conics, opacities, g, packed[g])
            _alpha_rect(packed[g], radii[g], tiles_x, tiles_y, tile_size, rects[g])


@njit(cache=True, nogil=True)
def listed(rects):
    """Ids [M] (ascending) of the Gaussians whose rect is not empty: the ones some tile lists."""
    count = 0
    for g in range(rects.shape[0]):
        count += rects[g, 1] > rects[g, 0]
    ids = np.empty(count, dtype=np.int64)
    m = 0
    for g in range(rects.shape[0]):
        if rects[g, 1] > rects[g, 0]:
            ids[m] = g
            m += 1
    return ids


RADIX_BITS = 11


def depth_order(depths: np.ndarray) -> np.ndarray:
    """Stable front-to-back order of ``depths`` [N] (float32 or float64), int64 [N]: an LSD radix
    sort on the floats' bit patterns, sign-folded so that unsigned order is float order (ties keep
    index order, as a stable argsort; -0.0 is folded onto 0.0 first)."""
    depths = np.ascontiguousarray(depths) + depths.dtype.type(0.0)  # -0.0 -> 0.0
    if depths.dtype == np.float32:
        bits = depths.view(np.uint32).astype(np.uint64)
        sign, width = np.uint64(1 << 31), 32
        keys = np.where(bits & sign, np.uint64(0xFFFFFFFF) ^ bits, bits | sign)
    else:
        bits = depths.astype(np.float64).view(np.uint64)
        sign, width = np.uint64(1 << 63), 64
        keys = np.where(bits & sign, ~bits, bits | sign)
    return _radix_order(keys, width)


@njit(cache=True, nogil=True)
def _radix_order(keys, width):
    """Stable order of the unsigned ``keys`` [N] (the low ``width`` bits), by RADIX_BITS digits."""
    n = keys.shape[0]
    order = np.arange(n)
    scratch = np.empty(n, dtype=np.int64)
    buckets = 1 << RADIX_BITS
    mask = np.uint64(buckets - 1)
    for shift in range(0, width, RADIX_BITS):
        counts = np.zeros(buckets + 1, dtype=np.int64)
        for i in range(n):
            counts[((keys[order[i]] >> np.uint64(shift)) & mask) + 1] += 1
        for b in range(buckets):
            counts[b + 1] += counts[b]
        for i in range(n):
            digit = (keys[order[i]] >> np.uint64(shift)) & mask
            scratch[counts[digit]] = order[i]
            counts[digit] += 1
        order, scratch = scratch, order
    return order


@njit(cache=True, nogil=True)
def alpha_tile_rects(packed, radii, tiles_x, tiles_y, tile_size):
    """[N, 4] int64 half-open tile ranges (x0, x1, y0, y1); empty for radius 0 (culled).

    The 3DGS support rule (the tiles the square [u - r, u + r] x [v - r, v + r] touches),
    narrowed to the tiles that the ellipse where alpha >= ALPHA_MIN can reach:
    opacity exp(-d^T Q d / 2) >= ALPHA_MIN  <=>  d^T Q d <= k^2 = 2 log(opacity / ALPHA_MIN),
    whose bounding box has half-widths k sqrt(Sigma_xx), k sqrt(Sigma_yy) (Sigma = Q^-1). Every
    pair this drops has alpha < ALPHA_MIN at every pixel of the tile, so it would be skipped
    anyway: the narrowing changes which pairs are visited, never the image or its gradients.
    """
    n = packed.shape[0]
    rects = np.zeros((n, 4), dtype=np.int64)
    for g in range(n):
        if radii[g] > 0:
            _alpha_rect(packed[g], radii[g], tiles_x, tiles_y, tile_size, rects[g])
    return rects


@njit(cache=True, inline="always")
def _alpha_rect(row, radius, tiles_x, tiles_y, tile_size, rect):
    """The tile rect (``alpha_tile_rects``) of one packed row with radius > 0 into rect [4]
    (left as it is, zeros, when empty)."""
    u, v, r = row[0], row[1], float(radius)
    lo_x, hi_x, lo_y, hi_y = u - r, u + r, v - r, v + r
    a, b, c, o = row[2], row[3], row[4], row[5]
    det = a * c - b * b
    if o * ALPHA_MAX < ALPHA_MIN:  # alpha < ALPHA_MIN everywhere (o exp(power) <= o)
        return
    if det > 0.0 and o > ALPHA_MIN:
        k2 = 2.0 * math.log(o / ALPHA_MIN)
        ex = math.sqrt(k2 * c / det) * (1.0 + 1e-6) + 1e-3  # conservative by a hair
        ey = math.sqrt(k2 * a / det) * (1.0 + 1e-6) + 1e-3
        lo_x, hi_x = max(lo_x, u - ex), min(hi_x, u + ex)
        lo_y, hi_y = max(lo_y, v - ey), min(hi_y, v + ey)
    elif o <= ALPHA_MIN:
        return
    x0 = min(max(math.floor(lo_x / tile_size), 0), tiles_x)
    x1 = min(max(math.floor(hi_x / tile_size) + 1, 0), tiles_x)
    y0 = min(max(math.floor(lo_y / tile_size), 0), tiles_y)
    y1 = min(max(math.floor(hi_y / tile_size) + 1, 0), tiles_y)
    if x1 > x0 and y1 > y0:
        rect[0], rect[1], rect[2], rect[3] = x0, x1, y0, y1


@njit(cache=True, nogil=True)
def bin_tiles(rects, depth_order, tiles_x, tiles_y):
    """Per-tile Gaussian lists in front-to-back order by a counting sort over tiles.

    rects [N, 4] from ``alpha_tile_rects``; depth_order [M] Gaussian ids front to back (stable):
    every Gaussian whose rect is not empty (``listed``), and any others (they add nothing).
    Returns gauss_ids [I], offsets [T], counts [T]: tile t's list is
    gauss_ids[offsets[t]:offsets[t] + counts[t]], in the order of ``depth_order``.
    """
    num_tiles = tiles_x * tiles_y
    counts = np.zeros(num_tiles, dtype=np.int64)
    for g in depth_order:
        for ty in range(rects[g, 2], rects[g, 3]):
            for tx in range(rects[g, 0], rects[g, 1]):
                counts[ty * tiles_x + tx] += 1
    offsets = np.zeros(num_tiles, dtype=np.int64)
    total = 0
    for t in range(num_tiles):
        offsets[t] = total
        total += counts[t]
    cursor = offsets.copy()
    gauss_ids = np.empty(total, dtype=np.int64)
    for g in depth_order:
        for ty in range(rects[g, 2], rects[g, 3]):
            for tx in range(rects[g, 0], rects[g, 1]):
                t = ty * tiles_x + tx
                gauss_ids[cursor[t]] = g
                cursor[t] += 1
    return gauss_ids, offsets, counts


@njit(cache=True, inline="always", fastmath={"nsz", "arcp", "contract", "afn", "reassoc"})
def _pair(px, py, row):
    """(alpha, live, dx, dy, e) of one Gaussian ``row`` (packed) at pixel centre (px, py).

    alpha 0 = skipped; live: unclamped, so d alpha / d power = alpha; e = exp(power).
    """
    dx, dy = px - row[0], py - row[1]
    power = -0.5 * (row[2] * dx * dx + row[4] * dy * dy) - row[3] * dx * dy
    if power > 0.0 or power < row[6] - SKIP_MARGIN:
        return 0.0, False, dx, dy, 0.0
    e = math.exp(power)
    alpha = row[5] * e
    if alpha < ALPHA_MIN:
        return 0.0, False, dx, dy, e
    if alpha < ALPHA_MAX:
        return alpha, True, dx, dy, e
    return ALPHA_MAX, False, dx, dy, e


@njit(cache=True, inline="always")
def _span(centre, extent, origin, size):
    """[first, stop) of the pixels k (0 <= k < size) of a tile row or column starting at pixel
    ``origin`` whose centre origin + k + 0.5 lies within ``extent`` of ``centre``: all of them
    when the extent is inf (or anything is NaN), none when it is negative."""
    if not extent < np.inf:
        return 0, size
    lo = centre - extent - origin - 0.5
    hi = centre + extent - origin - 0.5
    if not (lo == lo and hi == hi):  # a NaN centre: no box, as an infinite extent
        return 0, size
    first = 0 if lo <= 0.0 else (size if lo >= size else int(math.ceil(lo)))
    stop = size if hi >= size - 1 else (0 if hi < 0.0 else int(math.floor(hi)) + 1)
    return first, max(stop, first)


@njit(cache=True, inline="always")
def _tile_box(t, tiles_x, tile_size, width, height):
    """(x0, y0, tw, th): tile t's first pixel and its size (edge tiles are cut by the image)."""
    x0, y0 = (t % tiles_x) * tile_size, (t // tiles_x) * tile_size
    return x0, y0, min(tile_size, width - x0), min(tile_size, height - y0)


@njit(cache=True, inline="always")
def _tile_pixels(t, tiles_x, tile_size, width, height, xs, ys):
    """Fill xs, ys with the image pixels of tile t (row-major); returns how many."""
    x0, y0 = (t % tiles_x) * tile_size, (t // tiles_x) * tile_size
    npix = 0
    for y in range(y0, min(y0 + tile_size, height)):
        for x in range(x0, min(x0 + tile_size, width)):
            xs[npix], ys[npix] = x, y
            npix += 1
    return npix


@njit(cache=True, error_model="numpy", fastmath={"nsz", "arcp", "contract", "afn", "reassoc"})
def _forward_tile(t, gauss_ids, offsets, counts, packed, features, tiles_x, tile_size, image,
                  final, walked):
    """One tile, Gaussian by Gaussian over the tile's pixels (each Gaussian's row is read once per
    tile); the walk ends when every pixel of the tile has terminated."""
    height, width, dim = image.shape
    xs = np.empty(tile_size * tile_size, dtype=np.int64)
    ys = np.empty(tile_size * tile_size, dtype=np.int64)
    npix = _tile_pixels(t, tiles_x, tile_size, width, height, xs, ys)
    px, py = xs[:npix] + 0.5, ys[:npix] + 0.5
    trans = np.ones(npix)
    acc = np.zeros((npix, dim))
    last = np.zeros(npix, dtype=np.int64)
    done = np.zeros(npix, dtype=np.bool_)
    ndone = 0
    x0, y0, tw, th = _tile_box(t, tiles_x, tile_size, width, height)
    start = offsets[t]
    for j in range(counts[t]):
        g = gauss_ids[start + j]
        row = packed[g]
        lx0, lx1 = _span(row[0], row[7], x0, tw)
        ly0, ly1 = _span(row[1], row[8], y0, th)
        for ly in range(ly0, ly1):
            for p in range(ly * tw + lx0, ly * tw + lx1):
                if done[p]:
                    continue
                alpha, _, _, _, _ = _pair(px[p], py[p], row)
                if alpha == 0.0:
                    continue
                after = trans[p] * (1.0 - alpha)
                if after < T_MIN:
                    done[p] = True
                    ndone += 1
                    continue
                w = alpha * trans[p]
                for k in range(dim):
                    acc[p, k] += w * features[g, k]
                trans[p] = after
                last[p] = j + 1
        if ndone == npix:
            break
    for p in range(npix):
        x, y = xs[p], ys[p]
        for k in range(dim):
            image[y, x, k] = acc[p, k]
        final[y, x] = trans[p]
        walked[y, x] = last[p]


@njit(parallel=PRANGE_ONLY, cache=True, nogil=True)
def composite_forward(gauss_ids, offsets, counts, packed, features, width, height, tiles_x,
                      tile_size, workers):
    """Front-to-back walk of every pixel over its tile's list.

    Returns image [H, W, D] (accumulated features; the features' dtype, accumulated in float64),
    final transmittance [H, W] float64 (the backward walks back from it) and
    walked [H, W] int64: the list length up to and including the pixel's last composited Gaussian.
    """
    image = np.zeros((height, width, features.shape[1]), dtype=features.dtype)
    final = np.ones((height, width), dtype=np.float64)
    walked = np.zeros((height, width), dtype=np.int64)
    num_tiles = offsets.shape[0]
    if workers == 1:  # no parallel region: no idle pool threads spinning beside the job
        for t in range(num_tiles):
            _forward_tile(t, gauss_ids, offsets, counts, packed, features, tiles_x, tile_size,
                          image, final, walked)
    else:
        for worker in prange(workers):
            for t in range(worker, num_tiles, workers):
                _forward_tile(t, gauss_ids, offsets, counts, packed, features, tiles_x, tile_size,
                              image, final, walked)
    return image, final, walked


@njit(cache=True, nogil=True)
def walked_rows(walked, offsets, gauss_ids, tiles_x, tile_size):
    """Rows for the walked prefix of every tile's list: (row_start [T], row_ids [R]).

    Tile t owns rows row_start[t] ... + (the longest walk of its pixels); row_ids gives each
    row's Gaussian. Intersections no pixel reached get no row (their derivatives are 0).
    """
    height, width = walked.shape
    num_tiles = offsets.shape[0]
    longest = np.zeros(num_tiles, dtype=np.int64)
    for y in range(height):
        for x in range(width):
            t = (y // tile_size) * tiles_x + x // tile_size
            longest[t] = max(longest[t], walked[y, x])
    row_start = np.zeros(num_tiles, dtype=np.int64)
    total = 0
    for t in range(num_tiles):
        row_start[t] = total
        total += longest[t]
    row_ids = np.empty(total, dtype=np.int64)
    for t in range(num_tiles):
        for j in range(longest[t]):
            row_ids[row_start[t] + j] = gauss_ids[offsets[t] + j]
    return row_start, row_ids


@njit(cache=True, error_model="numpy", fastmath={"nsz", "arcp", "contract", "afn", "reassoc"})
def _backward_tile(t, gauss_ids, offsets, row_start, packed, features, final, walked, grad_image,
                   grad_final, tiles_x, tile_size, grads):
    """One tile back to front, Gaussian by Gaussian over the pixels that composited it; each
    Gaussian's gradient is summed over the tile's pixels locally and written to its row once."""
    height, width, dim = grad_image.shape
    xs = np.empty(tile_size * tile_size, dtype=np.int64)
    ys = np.empty(tile_size * tile_size, dtype=np.int64)
    npix = _tile_pixels(t, tiles_x, tile_size, width, height, xs, ys)
    px, py = xs[:npix] + 0.5, ys[:npix] + 0.5
    trans, behind = np.empty(npix), np.empty(npix)
    upstream = np.empty((npix, dim))
    ends = np.empty(npix, dtype=np.int64)
    longest = 0
    for p in range(npix):
        x, y = xs[p], ys[p]
        trans[p] = final[y, x]
        behind[p] = grad_final[y, x] * final[y, x]
        ends[p] = walked[y, x]
        longest = max(longest, ends[p])
        for k in range(dim):
            upstream[p, k] = grad_image[y, x, k]
    local = np.empty(6 + dim)
    x0, y0, tw, th = _tile_box(t, tiles_x, tile_size, width, height)
    start, rows = offsets[t], row_start[t]
    for j in range(longest - 1, -1, -1):
        g = gauss_ids[start + j]
        row = packed[g]
        a, b, c = row[2], row[3], row[4]
        local[:] = 0.0
        lx0, lx1 = _span(row[0], row[7], x0, tw)
        ly0, ly1 = _span(row[1], row[8], y0, th)
        for ly in range(ly0, ly1):
            for p in range(ly * tw + lx0, ly * tw + lx1):
                if j >= ends[p]:
                    continue
                alpha, live, dx, dy, e = _pair(px[p], py[p], row)
                if alpha == 0.0:
                    continue
                tr = trans[p] / (1.0 - alpha)
                trans[p] = tr
                w = alpha * tr
                q = 0.0
                for k in range(dim):
                    q += upstream[p, k] * features[g, k]
                    local[6 + k] += w * upstream[p, k]
                d_alpha = tr * q - behind[p] / (1.0 - alpha)
                behind[p] += w * q
                if not live:
                    continue
                d_power = d_alpha * alpha
                local[0] += d_power * (a * dx + b * dy)
                local[1] += d_power * (b * dx + c * dy)
                local[2] -= 0.5 * d_power * dx * dx
                local[3] -= d_power * dx * dy
                local[4] -= 0.5 * d_power * dy * dy
                local[5] += d_alpha * e
        out = grads[rows + j]
        for k in range(6 + dim):
            out[k] = local[k]


@njit(parallel=PRANGE_ONLY, cache=True, nogil=True)
def composite_backward(gauss_ids, offsets, row_start, num_rows, packed, features, final, walked,
                       grad_image, grad_final, tiles_x, tile_size, workers):
    """Gradient rows [R, 6 + D] float64 (u, v, conic a, b, c, opacity, features), one per walked
    intersection (``walked_rows``).

    Walks each pixel's composited Gaussians back to front, recovering the transmittance before
    Gaussian k as T_k = T_{k+1} / (1 - alpha_k) (alpha <= ALPHA_MAX, so no division by ~0):
        dL/dalpha_k = T_k q_k - (sum_{i>k} w_i q_i + dL/dT_final T_final) / (1 - alpha_k),
    with q_k = dL/dimage . f_k and w_k = alpha_k T_k; a clamped alpha passes no gradient on.
    """
    grads = np.zeros((num_rows, 6 + grad_image.shape[2]), dtype=np.float64)
    num_tiles = offsets.shape[0]
    if workers == 1:  # no parallel region: no idle pool threads spinning beside the job
        for t in range(num_tiles):
            _backward_tile(t, gauss_ids, offsets, row_start, packed, features, final, walked,
                           grad_image, grad_final, tiles_x, tile_size, grads)
    else:
        for worker in prange(workers):
            for t in range(worker, num_tiles, workers):
                _backward_tile(t, gauss_ids, offsets, row_start, packed, features, final, walked,
                               grad_image, grad_final, tiles_x, tile_size, grads)
    return grads


@njit(cache=True, inline="always", fastmath={"nsz", "arcp", "contract", "afn", "reassoc"})
def _fisher_pair(p, g, row, alpha, live, dx, dy, colors, channel_summed, trans, suffix, h, s,
                 local):
    """One (pixel p, Gaussian g) pair of the walk back to front: recover the transmittance before g
    (trans[p] / (1 - alpha)), add g's colour to what lies behind (suffix), and add the pair's terms
    to the Fisher row ``local`` [40] (``fisher_rows``). h[5] = 1 / opacity is the caller's."""
    tr = trans[p] / (1.0 - alpha)
    trans[p] = tr
    w = alpha * tr
    odds = alpha / (1.0 - alpha)
    total, summed = 0.0, 0.0
    for c in range(3):
        s[c] = (w * colors[g, c] - odds * suffix[p, c]) if live else 0.0
        suffix[p, c] += w * colors[g, c]
        total += s[c] * s[c]
        summed += s[c]
    if channel_summed:
        total = summed * summed
    h[0] = row[2] * dx + row[3] * dy
    h[1] = row[3] * dx + row[4] * dy
    h[2] = -0.5 * dx * dx
    h[3] = -dx * dy
    h[4] = -0.5 * dy * dy
    k = 0
    for a in range(6):
        sh = total * h[a]
        for b in range(a, 6):
            local[k] += sh * h[b]
            k += 1
    for a in range(6):
        for c in range(3):
            local[21 + 3 * a + c] += s[c] * w * h[a]
    local[39] += w * w


@njit(cache=True, error_model="numpy", fastmath={"nsz", "arcp", "contract", "afn", "reassoc"})
def _fisher_tile(t, gauss_ids, offsets, row_start, packed, colors, final, walked, background,
                 tiles_x, tile_size, channel_summed, rows_out):
    """One tile back to front, Gaussian by Gaussian; each Gaussian's 40 sums are accumulated over
    the tile's pixels locally and written to its row once."""
    height, width = walked.shape
    xs = np.empty(tile_size * tile_size, dtype=np.int64)
    ys = np.empty(tile_size * tile_size, dtype=np.int64)
    npix = _tile_pixels(t, tiles_x, tile_size, width, height, xs, ys)
    px, py = xs[:npix] + 0.5, ys[:npix] + 0.5
    trans = np.empty(npix)
    suffix = np.empty((npix, 3))
    ends = np.empty(npix, dtype=np.int64)
    longest = 0
    for p in range(npix):
        x, y = xs[p], ys[p]
        trans[p] = final[y, x]
        ends[p] = walked[y, x]
        longest = max(longest, ends[p])
        for c in range(3):
            suffix[p, c] = final[y, x] * background[c]
    h = np.empty(6)
    s = np.empty(3)
    local = np.empty(FISHER_ROW)
    x0, y0, tw, th = _tile_box(t, tiles_x, tile_size, width, height)
    start, rows = offsets[t], row_start[t]
    for j in range(longest - 1, -1, -1):
        g = gauss_ids[start + j]
        row = packed[g]
        local[:] = 0.0
        h[5] = 1.0 / row[5]
        lx0, lx1 = _span(row[0], row[7], x0, tw)
        ly0, ly1 = _span(row[1], row[8], y0, th)
        for ly in range(ly0, ly1):
            for p in range(ly * tw + lx0, ly * tw + lx1):
                if j >= ends[p]:
                    continue
                alpha, live, dx, dy, _ = _pair(px[p], py[p], row)
                if alpha == 0.0:
                    continue
                _fisher_pair(p, g, row, alpha, live, dx, dy, colors, channel_summed, trans,
                             suffix, h, s, local)
        out = rows_out[rows + j]
        for k in range(FISHER_ROW):
            out[k] = local[k]


@njit(parallel=PRANGE_ONLY, cache=True, nogil=True)
def fisher_rows(gauss_ids, offsets, row_start, num_rows, packed, colors, final, walked,
                background, tiles_x, tile_size, channel_summed, workers):
    """Per walked intersection, the pixel sums of the feature-space Fisher pieces, [R, 40] float64.

    Per (pixel, Gaussian): s_c = dI_c / d(exponent) (0 where alpha is clamped), w = alpha T,
    h = d(exponent) / d(u, v, a, b, c, opacity) at the pixel's offset d from the mean:
        h = (a dx + b dy, b dx + c dy, -dx^2 / 2, -dx dy, -dy^2 / 2, 1 / opacity).
    Row = (sum S h_a h_b for a <= b [21], sum s_c w h_a [6 x 3], sum w^2), S = sum_c s_c^2, or
    S = (sum_c s_c)^2 when ``channel_summed`` (FisherRF's released Hessian squares the
    channel-summed derivative).
    The exponent's derivative s_c = w f_c - alpha / (1 - alpha) * (colour composited behind,
    background times final transmittance included), accumulated back to front.
    """
    out = np.zeros((num_rows, FISHER_ROW), dtype=np.float64)
    num_tiles = offsets.shape[0]
    if workers == 1:  # no parallel region: no idle pool threads spinning beside the job
        for t in range(num_tiles):
            _fisher_tile(t, gauss_ids, offsets, row_start, packed, colors, final, walked,
                         background, tiles_x, tile_size, channel_summed, out)
    else:
        for worker in prange(workers):
            for t in range(worker, num_tiles, workers):
                _fisher_tile(t, gauss_ids, offsets, row_start, packed, colors, final, walked,
                             background, tiles_x, tile_size, channel_summed, out)
    return out


@njit(cache=True, nogil=True)
def sum_rows(row_ids, rows, n, like):
    """Per-Gaussian sums [n, K] (dtype of ``like``) of rows [R, K] by their Gaussian ids [R], in
    row order: deterministic whatever the thread schedule that wrote the rows."""
    out = np.zeros((n, rows.shape[1]), dtype=np.float64)
    for r in range(rows.shape[0]):
        g = row_ids[r]
        for k in range(rows.shape[1]):
            out[g, k] += rows[r, k]
    return out.astype(like.dtype)


@njit(cache=True, error_model="numpy", fastmath={"nsz", "arcp", "contract", "afn", "reassoc"})
def _walk_fisher_tile(t, gauss_ids, offsets, counts, packed, colors, background, width, height,
                      tiles_x, tile_size, channel_summed, alphas, rows_out):
    """One tile's forward walk and Fisher walk back to back (``_forward_tile`` without features,
    then ``_fisher_tile``): the forward keeps each composited pair's alpha in ``alphas``
    [>= counts[t], tile_size^2] (0 for a pair it skipped or never reached), so the walk back reads
    it instead of recomputing the pair (its exponential), and no pixel needs a walked length:
    a zero alpha is a pair the pixel never composited. Both walks visit only the pair's box
    (``_span``), so alphas outside it are never written or read. Rows go to
    rows_out[offsets[t] + j]; returns the tile's walked length (the rows written are j < it)."""
    xs = np.empty(tile_size * tile_size, dtype=np.int64)
    ys = np.empty(tile_size * tile_size, dtype=np.int64)
    npix = _tile_pixels(t, tiles_x, tile_size, width, height, xs, ys)
    px, py = xs[:npix] + 0.5, ys[:npix] + 0.5
    trans = np.ones(npix)
    done = np.zeros(npix, dtype=np.bool_)
    ndone, longest = 0, 0
    x0, y0, tw, th = _tile_box(t, tiles_x, tile_size, width, height)
    start, count = offsets[t], counts[t]
    for j in range(count):
        row = packed[gauss_ids[start + j]]
        lx0, lx1 = _span(row[0], row[7], x0, tw)
        ly0, ly1 = _span(row[1], row[8], y0, th)
        for ly in range(ly0, ly1):  # the walk back reads this box only
            for p in range(ly * tw + lx0, ly * tw + lx1):
                alphas[j, p] = 0.0
                if done[p]:
                    continue
                alpha, _, _, _, _ = _pair(px[p], py[p], row)
                if alpha == 0.0:
                    continue
                after = trans[p] * (1.0 - alpha)
                if after < T_MIN:
                    done[p] = True
                    ndone += 1
                    continue
                alphas[j, p] = alpha
                trans[p] = after
                longest = j + 1
        if ndone == npix:
            break
    suffix = np.empty((npix, 3))
    for p in range(npix):
        for c in range(3):
            suffix[p, c] = trans[p] * background[c]
    h = np.empty(6)
    s = np.empty(3)
    local = np.empty(FISHER_ROW)
    for j in range(longest - 1, -1, -1):
        g = gauss_ids[start + j]
        row = packed[g]
        local[:] = 0.0
        h[5] = 1.0 / row[5]
        lx0, lx1 = _span(row[0], row[7], x0, tw)
        ly0, ly1 = _span(row[1], row[8], y0, th)
        for ly in range(ly0, ly1):
            for p in range(ly * tw + lx0, ly * tw + lx1):
                alpha = alphas[j, p]
                if alpha == 0.0:
                    continue
                live = alpha < ALPHA_MAX  # ``_pair`` clamps at ALPHA_MAX exactly when not live
                _fisher_pair(p, g, row, alpha, live, px[p] - row[0], py[p] - row[1], colors,
                             channel_summed, trans, suffix, h, s, local)
        out = rows_out[start + j]
        for k in range(FISHER_ROW):
            out[k] = local[k]
    return longest


@njit(cache=True, nogil=True)
def _walk_fisher_tiles(first, step, gauss_ids, offsets, counts, packed, colors, background, width,
                       height, tiles_x, tile_size, channel_summed, longest, rows):
    """Tiles first, first + step, ... of ``walk_fisher``, with an alpha buffer of their own."""
    most = 0
    for t in range(first, offsets.shape[0], step):
        most = max(most, counts[t])
    alphas = np.empty((most, tile_size * tile_size))
    for t in range(first, offsets.shape[0], step):
        longest[t] = _walk_fisher_tile(t, gauss_ids, offsets, counts, packed, colors, background,
                                       width, height, tiles_x, tile_size, channel_summed, alphas,
                                       rows)


@njit(parallel=PRANGE_ONLY, cache=True, nogil=True)
def walk_fisher(gauss_ids, offsets, counts, packed, colors, background, width, height, tiles_x,
                tile_size, channel_summed, workers):
    """``composite_forward`` (transmittance only), ``walked_rows`` and ``fisher_rows`` of one view
    in one pass, tile by tile (``_walk_fisher_tile``; the tiles interleaved over ``workers``).
    Returns (longest [T], rows [I, 40]): the Fisher rows of the intersections offsets[t] + j for
    j < longest[t] (the walked ones; the other rows are unset). The same rows as ``fisher_rows``
    to float rounding (the pair's alpha is kept, not recomputed)."""
    num_tiles = offsets.shape[0]
    rows = np.empty((gauss_ids.shape[0], FISHER_ROW))
    longest = np.zeros(num_tiles, dtype=np.int64)
    if workers == 1:  # no parallel region: no idle pool threads spinning beside the job
        _walk_fisher_tiles(0, 1, gauss_ids, offsets, counts, packed, colors, background, width,
                           height, tiles_x, tile_size, channel_summed, longest, rows)
    else:
        for worker in prange(workers):
            _walk_fisher_tiles(worker, workers, gauss_ids, offsets, counts, packed, colors,
                               background, width, height, tiles_x, tile_size, channel_summed,
                               longest, rows)
    return longest, rows


@njit(cache=True, nogil=True)
def sum_walked_rows(gauss_ids, offsets, longest, rows, n):
    """``sum_rows`` of ``walk_fisher``'s rows, for only the Gaussians they reach: (ids [M] sorted,
    sums [M, K] float64) over the walked intersections (offsets[t] + j, j < longest[t]), each
    Gaussian's rows added in tile order, the row order of ``walked_rows`` (so every sum equals
    ``sum_rows``'s of those rows to the bit), without the [n, K] block that is mostly zeros when
    few Gaussians are reached."""
    slot = np.full(n, -1, dtype=np.int64)
    for t in range(offsets.shape[0]):
        for j in range(longest[t]):
            slot[gauss_ids[offsets[t] + j]] = 0
    m = 0
    for g in range(n):
        if slot[g] == 0:
            slot[g] = m
            m += 1
    ids = np.empty(m, dtype=np.int64)
    for g in range(n):
        if slot[g] >= 0:
            ids[slot[g]] = g
    out = np.zeros((m, rows.shape[1]), dtype=np.float64)
    for t in range(offsets.shape[0]):
        for j in range(longest[t]):
            r = offsets[t] + j
            i = slot[gauss_ids[r]]
            for k in range(rows.shape[1]):
                out[i, k] += rows[r, k]
    return ids, out
