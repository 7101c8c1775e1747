"""Compiled (numba) 3DGS training loss, value and gradient in one pass: the fused twin of
``losses.photometric_loss`` (the oracle; tests compare them).

    L = (1 - w) mean|x - y| + w (1 - mean SSIM(x, y)),  means over H x W x 3,

SSIM with the 11 x 11 Gaussian window (sigma 1.5), zero-padded 'same' windows, per channel, as
``losses.ssim_map``. The window is separable (g g^T), so each of the five local means is two 1-D
passes (22 taps a pixel instead of 121). The gradient w.r.t. x is analytic: with
    A1 = 2 mu_x mu_y + C1, A2 = 2 s_xy + C2, B1 = mu_x^2 + mu_y^2 + C1, B2 = s_xx + s_yy + C2,
    S = A1 A2 / (B1 B2), s_xx = E[x^2] - mu_x^2, s_xy = E[xy] - mu_x mu_y,
the map's derivatives w.r.t. the local means mu_x, E[x^2], E[xy] are
    dS/dmu_x  = 2 mu_y (A2 - A1) / (B1 B2) - 2 mu_x S (1 / B1 - 1 / B2),
    dS/dE[x^2] = -S / B2,   dS/dE[xy] = 2 A1 / (B1 B2),
and a local mean's transpose is the same zero-padded window (it is symmetric), so
    d mean S / dx = (G * dS/dmu_x + 2 x G * dS/dE[x^2] + y G * dS/dE[xy]) / (H W 3).
The L1 part's derivative is sign(x - y) / (H W 3) (0 where x = y, as torch's). Arithmetic is
float64 whatever the images' dtype; the gradient is returned in float64 and cast by the caller.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from pipeline.splat.kernels import PRANGE_ONLY

C1, C2 = 0.01 ** 2, 0.03 ** 2


def gaussian_taps(size: int = 11, sigma: float = 1.5) -> np.ndarray:
    """The normalised 1-D window [size] float64 (its outer product is ``losses._window``)."""
    x = np.arange(size, dtype=np.float64) - (size - 1) / 2
    g = np.exp(-(x * x) / (2 * sigma * sigma))
    return g / g.sum()


@njit(parallel=PRANGE_ONLY, cache=True, nogil=True)
def _blur(src, taps, out, workers):
    """out = G * src, zero-padded 'same', for src [K, H, W] (each plane separately), the planes
    interleaved over ``workers`` (each plane's arithmetic is the same whoever blurs it)."""
    if workers == 1:  # no parallel region: no idle pool threads spinning beside the job
        _blur_planes(src, taps, out, 0, 1)
    else:
        for w in prange(workers):
            _blur_planes(src, taps, out, w, workers)


@njit(cache=True, nogil=True)
def _blur_planes(src, taps, out, first, step):
    """Planes first, first + step, ... of ``_blur``: a horizontal then a vertical 1-D pass over
    zero-padded copies, the inner loop along a row (vectorised)."""
    planes, height, width = src.shape
    size = taps.shape[0]
    r = size // 2
    wide = np.zeros((height, width + 2 * r))
    tall = np.zeros((height + 2 * r, width))
    for k in range(first, planes, step):
        for i in range(height):
            for j in range(width):
                wide[i, r + j] = src[k, i, j]
        for i in range(height):
            row = tall[r + i]
            row[:] = 0.0
            for t in range(size):
                tap = taps[t]
                for j in range(width):
                    row[j] += tap * wide[i, j + t]
        for i in range(height):
            for j in range(width):
                out[k, i, j] = 0.0
            for t in range(size):
                tap = taps[t]
                for j in range(width):
                    out[k, i, j] += tap * tall[i + t, j]


@njit(cache=True, nogil=True, error_model="numpy")
def photometric_value_and_grad(image, target, ssim_weight, taps, workers):
    """(loss float64, dloss/dimage [H, W, 3] float64) of image, target [H, W, 3] (any float); the
    window's passes on ``workers`` threads (the rest, ~a fifth, on one)."""
    height, width, channels = image.shape
    n = height * width * channels
    stack = np.empty((5 * channels, height, width))
    for c in range(channels):
        for i in range(height):
            for j in range(width):
                x, y = float(image[i, j, c]), float(target[i, j, c])
                stack[c, i, j] = x
                stack[channels + c, i, j] = y
                stack[2 * channels + c, i, j] = x * x
                stack[3 * channels + c, i, j] = y * y
                stack[4 * channels + c, i, j] = x * y
    means = np.empty_like(stack)
    _blur(stack, taps, means, workers)
    dmaps = np.empty((3 * channels, height, width))  # dS/dmu_x, dS/dE[x^2], dS/dE[xy]
    ssim_sum, l1_sum = 0.0, 0.0
    for c in range(channels):
        for i in range(height):
            for j in range(width):
                mx, my = means[c, i, j], means[channels + c, i, j]
                sxx = means[2 * channels + c, i, j] - mx * mx
                syy = means[3 * channels + c, i, j] - my * my
                sxy = means[4 * channels + c, i, j] - mx * my
                a1, a2 = 2 * mx * my + C1, 2 * sxy + C2
                b1, b2 = mx * mx + my * my + C1, sxx + syy + C2
                den = b1 * b2
                s = a1 * a2 / den
                ssim_sum += s
                dmaps[c, i, j] = 2 * my * (a2 - a1) / den - 2 * mx * s * (1 / b1 - 1 / b2)
                dmaps[channels + c, i, j] = -s / b2
                dmaps[2 * channels + c, i, j] = 2 * a1 / den
    back = np.empty_like(dmaps)
    _blur(dmaps, taps, back, workers)
    grad = np.empty((height, width, channels))
    w_l1, w_ssim = (1 - ssim_weight) / n, ssim_weight / n
    for c in range(channels):
        for i in range(height):
            for j in range(width):
                x, y = float(image[i, j, c]), float(target[i, j, c])
                diff = x - y
                l1_sum += math.fabs(diff)
                sign = 1.0 if diff > 0 else (-1.0 if diff < 0 else 0.0)
                dssim = back[c, i, j] + 2 * x * back[channels + c, i, j] + \
                    y * back[2 * channels + c, i, j]
                grad[i, j, c] = w_l1 * sign - w_ssim * dssim
    loss = (1 - ssim_weight) * l1_sum / n + ssim_weight * (1 - ssim_sum / n)
    return loss, grad
