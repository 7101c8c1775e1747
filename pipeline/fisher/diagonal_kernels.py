"""Compiled (numba) per-view Fisher diagonal: the walk's per-Gaussian sums -> diag(A^T G A) rows.

The fused tail of ``exact.view_fisher`` on the compiled backend. Per Gaussian the walk left 40
pixel sums (``splat.kernels.fisher_rows``, summed per Gaussian); from them this lays out the 9x9
feature Fisher G exactly as ``exact.assemble_feature_fisher`` does, computes the Gaussian's
feature Jacobian A (``splat.project_kernels.jacobian_one``, the kernel of
``features.feature_jacobian_compiled``) and writes diag(A^T G A) of the Gaussians the walk
reached as compact [M, P] rows, as ``features.FeatureJacobian.fisher_diagonal`` (the oracle; tests compare).
``channel_summed`` applies FisherRF's released rule as ``exact.activated_once`` does: the
log-scale columns become quad(A) / scale, the opacity column G_oo * sigmoid'.
Nothing per Gaussian leaves the kernel: no [M, 9, 9] G, no [M, 8, 10] Jacobian tensors.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from pipeline.splat.kernels import PRANGE_ONLY
from pipeline.splat.project_kernels import chain_scratch, jacobian_one

# feature index (u, v, a, b, c, opacity, r, g, b) of each of the Jacobian's 8 geometric rows
GEOMETRIC_FEATURES = np.array([0, 1, 2, 3, 4, 6, 7, 8])
# group order of the flattened layout (``features.PARAM_GROUPS``)
MEANS, LOG_SCALES, QUATS, OPACITY, SH0, SHN = range(6)


@njit(cache=True, inline="always")
def _feature_fisher(sums, channel_summed, G):
    """G [9, 9] from one Gaussian's 40 walk sums (``assemble_feature_fisher``'s layout)."""
    k = 0
    for a in range(6):
        for b in range(a, 6):
            G[a, b] = G[b, a] = sums[k]
            k += 1
    w2 = sums[39]
    for a in range(6):
        total = sums[21 + 3 * a] + sums[22 + 3 * a] + sums[23 + 3 * a]
        for c in range(3):
            cross = total if channel_summed else sums[21 + 3 * a + c]
            G[a, 6 + c] = G[6 + c, a] = cross
    for c in range(3):
        for d in range(3):
            G[6 + c, 6 + d] = w2 if (channel_summed or c == d) else 0.0


@njit(cache=True, error_model="numpy")
def _diagonal_block(lo, hi, ids, sums, means, log_scales, quats, logit_opacities, sh0, shn, view,
                    intr, width, height, sh_degree, near, groups, channel_summed, out):
    scratch = chain_scratch()
    geometry = np.empty((8, 10))
    sh_slope = np.empty((shn.shape[1] + 1, 3))
    G = np.empty((9, 9))
    quad = np.empty(10)
    rows = GEOMETRIC_FEATURES
    for j in range(lo, hi):
        g = ids[j]
        sh_slope[:] = 0.0
        slope = jacobian_one(g, means, log_scales, quats, logit_opacities, sh0, shn, view, intr,
                             width, height, sh_degree, near, scratch, geometry, sh_slope)
        _feature_fisher(sums[j], channel_summed, G)
        for q in range(10):  # sum_rs G_rs A_rq A_sq over the geometric rows
            acc = 0.0
            for r in range(8):
                ar = geometry[r, q]
                if ar == 0.0:
                    continue
                inner = 0.0
                for s_ in range(8):
                    inner += G[rows[r], rows[s_]] * geometry[s_, q]
                acc += ar * inner
            quad[q] = acc
        col = 0
        if groups[MEANS]:
            for q in range(3):
                out[j, col] = quad[q]
                col += 1
        if groups[LOG_SCALES]:
            for q in range(3, 6):
                # released rule: the Jacobian w.r.t. the scale (A / s), the factor s applied once
                out[j, col] = quad[q] / math.exp(log_scales[g, q - 3]) if channel_summed else quad[q]
                col += 1
        if groups[QUATS]:
            for q in range(6, 10):
                out[j, col] = quad[q]
                col += 1
        if groups[OPACITY]:
            out[j, col] = G[5, 5] * slope if channel_summed else G[5, 5] * slope * slope
            col += 1
        if groups[SH0]:
            for c in range(3):
                out[j, col] = sh_slope[0, c] * sh_slope[0, c] * G[6 + c, 6 + c]
                col += 1
        if groups[SHN]:
            for k in range(1, sh_slope.shape[0]):
                for c in range(3):
                    out[j, col] = sh_slope[k, c] * sh_slope[k, c] * G[6 + c, 6 + c]
                    col += 1


@njit(parallel=PRANGE_ONLY, cache=True, nogil=True)
def fisher_diagonal(ids, sums, means, log_scales, quats, logit_opacities, sh0, shn, view, intr,
                    width, height, sh_degree, near, groups, channel_summed, out, workers):
    """Write diag(A^T G A) of Gaussian ids[j] into out[j] [M, P] float64 for the M Gaussians the
    walk reached (every other Gaussian's Fisher is zero). sums [M, 40] float64 their walk sums;
    groups [6] bool: which of ``PARAM_GROUPS`` the P columns hold, in that order."""
    m = ids.shape[0]
    if workers == 1:  # no parallel region: no idle pool threads spinning beside the job
        _diagonal_block(0, m, ids, sums, means, log_scales, quats, logit_opacities, sh0, shn,
                        view, intr, width, height, sh_degree, near, groups, channel_summed, out)
    else:
        for w in prange(workers):
            _diagonal_block(w * m // workers, (w + 1) * m // workers, ids, sums, means,
                            log_scales, quats, logit_opacities, sh0, shn, view, intr, width,
                            height, sh_degree, near, groups, channel_summed, out)
