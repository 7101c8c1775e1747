"""Pixel-level uncertainty metrics, as the field's released code computes them (each convention named).

Inputs are flat per-pixel arrays of one test view (or of several, concatenated): ``error`` [P] (a
per-pixel error: absolute, squared or DSSIM) and ``uncertainty`` [P] (any score whose larger values
mean less trust). Higher-level callers choose the error:

- MAE: the absolute RGB error summed over channels (AaltoML/uncertainty-nerf-gs) or its channel mean
  (3DGS-Uncertainty); RMSE: the squared error summed over channels, the curve the root of the kept
  mean; DSSIM: 1 - SSIM map (3DGS-Uncertainty), channel mean.

Sparsification (Ilg et al. 2018): remove the most uncertain fraction r of the pixels, take the error
of the rest; the oracle removes the truly worst first; the random ranking removes pixels uniformly,
whose expected curve is flat at the error of all pixels (``random_curve``). Ties in the uncertainty
are resolved in expectation: a group of equal values at the cut contributes its own mean for the part
of it that is kept, so a constant uncertainty gives the random curve exactly. AUSE is the area between
the method's curve and the oracle's. Two normalisations are in use and give different numbers:

- ``ause_max``: removal fractions ``linspace(0, 1, 100, endpoint=False)``, both curves divided by the
  largest value of either, trapezoid over the fractions (FisherRF's, WarpRF's and AaltoML's released
  ``ause``);
- ``ause_start``: fractions ``linspace(0, 0.999, 100)``, pixels with zero error or zero uncertainty
  dropped first, both curves divided by the oracle's start (the mean error of all pixels), trapezoid
  over the first 99 fractions (the 3DGS-Uncertainty code's ``ause_torch``).

Calibration, where the map is a predicted standard deviation (not a score):

- ``gaussian_nll``: the mean over pixels and channels of -log N(target | mean, max(sigma, floor)^2),
  floor 0.03 on RGB and 1.0 on depth (AaltoML's ``negative_gaussian_loglikelihood``);
- ``auce``: for alpha in 0.01 ... 0.99, the coverage of the intervals mean +- z_{1-alpha/2} sigma, its
  absolute difference from 1 - alpha, trapezoid over alpha (AaltoML's ``auce``, after evaluating_bdl);
- ``correlations``: Pearson's r (3DGS-Uncertainty reports it) and Spearman's rho (ranks, ties averaged)
  between uncertainty and error.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

MAX_FRACTIONS = np.linspace(0.0, 1.0, 100, endpoint=False)
START_FRACTIONS = np.linspace(0.0, 0.999, 100)
RGB_SIGMA_FLOOR = 0.03
DEPTH_SIGMA_FLOOR = 1.0
AUCE_ALPHAS = np.arange(1, 100) / 100.0


def _vectors(error, uncertainty) -> tuple[np.ndarray, np.ndarray]:
    e, u = np.asarray(error, dtype=np.float64).ravel(), np.asarray(uncertainty, dtype=np.float64).ravel()
    if e.shape != u.shape or e.size == 0:
        raise ValueError(f"error and uncertainty must be equal-size arrays, got {np.shape(error)} and {np.shape(uncertainty)}")
    if not (np.isfinite(e).all() and np.isfinite(u).all()):
        raise ValueError("error and uncertainty must be finite")
    return e, u


def kept_means(values: np.ndarray, order_key: np.ndarray, fractions: np.ndarray) -> np.ndarray:
    """[F] mean of ``values`` over the pixels kept after removing the fraction f with the largest
    ``order_key``, ties in the key taken in expectation (see the module's text). At least one pixel is kept."""
    order = np.argsort(order_key, kind="stable")                       # ascending: kept first
    v, k = values[order], order_key[order]
    n = len(v)
    starts = np.flatnonzero(np.r_[True, k[1:] != k[:-1]])              # first index of each tie group
    ends = np.r_[starts[1:], n]
    group_sum = np.add.reduceat(v, starts)
    group_len = ends - starts
    before = np.r_[0.0, np.cumsum(group_sum)]                         # sum of whole groups before group g
    out = []
    for f in fractions:
        kept = max(1, int((1.0 - f) * n))
        g = np.searchsorted(ends, kept, side="left")                  # the group the cut falls in
        inside = kept - starts[g]
        out.append((before[g] + inside * group_sum[g] / group_len[g]) / kept)
    return np.array(out)


@dataclass(frozen=True)
class Sparsification:
    """The curves of one map at ``fractions``: by the uncertainty, the oracle's, the random one."""

    fractions: np.ndarray
    by_uncertainty: np.ndarray
    oracle: np.ndarray
    random: np.ndarray


def sparsification(error, uncertainty, fractions=MAX_FRACTIONS, root: bool = False) -> Sparsification:
    """The error of the kept pixels at each removal fraction; ``root``: the square root of the kept
    mean (RMSE, ``error`` holding squared errors)."""
    e, u = _vectors(error, uncertainty)
    f = np.asarray(fractions, dtype=np.float64)
    post = np.sqrt if root else (lambda x: x)
    return Sparsification(f, post(kept_means(e, u, f)), post(kept_means(e, e, f)),
                          post(np.full(len(f), e.mean())))


def random_curve(error, fractions=MAX_FRACTIONS, root: bool = False) -> np.ndarray:
    """The expected curve of a uniformly random ranking: the error of all pixels at every fraction."""
    e = np.asarray(error, dtype=np.float64).ravel()
    return np.full(len(fractions), math.sqrt(e.mean()) if root else e.mean())


def ause_max(error, uncertainty, root: bool = False) -> tuple[float, Sparsification]:
    """AUSE with both curves divided by their largest value (FisherRF, WarpRF, AaltoML)."""
    s = sparsification(error, uncertainty, MAX_FRACTIONS, root)
    top = max(s.by_uncertainty.max(), s.oracle.max())
    if top <= 0:
        return 0.0, s
    return float(np.trapezoid((s.by_uncertainty - s.oracle) / top, s.fractions)), s


def ause_start(error, uncertainty, root: bool = False) -> tuple[float, Sparsification]:
    """AUSE with both curves divided by the oracle's start value, zero-error and zero-uncertainty
    pixels dropped, the last fraction (0.999) left out (3DGS-Uncertainty)."""
    e, u = _vectors(error, uncertainty)
    keep = (e != 0) & (u != 0)
    if not keep.any():
        return 0.0, sparsification(np.zeros(1), np.zeros(1), START_FRACTIONS[:-1], root)
    s = sparsification(e[keep], u[keep], START_FRACTIONS[:-1], root)
    start = s.oracle[0]
    return float(np.trapezoid((s.by_uncertainty - s.oracle) / start, s.fractions)), s


def gaussian_nll(mean, target, sigma, floor: float = RGB_SIGMA_FLOOR) -> float:
    """Mean negative log-likelihood of ``target`` [P, C] under N(``mean`` [P, C], max(sigma, floor)^2);
    ``sigma`` [P] (one per pixel, shared by its channels) or [P, C]."""
    m, t = np.asarray(mean, dtype=np.float64), np.asarray(target, dtype=np.float64)
    s = np.asarray(sigma, dtype=np.float64)
    if s.ndim == m.ndim - 1:
        s = s[..., None]
    s = np.maximum(np.broadcast_to(s, m.shape), floor)
    return float(np.mean(0.5 * np.log(2 * np.pi * s ** 2) + (t - m) ** 2 / (2 * s ** 2)))


def _normal_quantile(p: np.ndarray) -> np.ndarray:
    from scipy.special import ndtri
    return ndtri(p)


def auce(mean, target, sigma, alphas=AUCE_ALPHAS) -> tuple[float, np.ndarray]:
    """Area under the absolute coverage-error curve and the coverage [A] of each interval
    mean +- z_{1-alpha/2} sigma (``sigma`` as in ``gaussian_nll``, no floor)."""
    m, t = np.asarray(mean, dtype=np.float64), np.asarray(target, dtype=np.float64)
    s = np.asarray(sigma, dtype=np.float64)
    if s.ndim == m.ndim - 1:
        s = s[..., None]
    s = np.broadcast_to(s, m.shape)
    a = np.asarray(alphas, dtype=np.float64)
    z = _normal_quantile(1.0 - a / 2)
    gap = np.abs(t - m).ravel()
    width = s.ravel()
    coverage = np.array([np.mean(gap <= zi * width) for zi in z])
    return float(np.trapezoid(np.abs(coverage - (1.0 - a)), a)), coverage


def _ranks(x: np.ndarray) -> np.ndarray:
    """Ranks 1..n, ties given their average rank."""
    order = np.argsort(x, kind="stable")
    ranks = np.empty(len(x))
    ranks[order] = np.arange(1, len(x) + 1)
    values, inverse = np.unique(x, return_inverse=True)
    sums = np.bincount(inverse, weights=ranks)
    counts = np.bincount(inverse)
    return (sums / counts)[inverse]


def _pearson(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a - a.mean(), b - b.mean()
    denominator = math.sqrt(float(a @ a) * float(b @ b))
    return float(a @ b / denominator) if denominator > 0 else float("nan")


def correlations(uncertainty, error) -> tuple[float, float]:
    """(Pearson's r, Spearman's rho) between the maps; NaN when either is constant."""
    e, u = _vectors(error, uncertainty)
    return _pearson(u, e), _pearson(_ranks(u), _ranks(e))
