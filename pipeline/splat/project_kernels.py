"""Compiled (numba) EWA projection + SH colour per Gaussian, and its hand-written backward.

The rules are ``project.py``'s, which stays the oracle (tests compare both, values and every raw
parameter's gradient). One Gaussian per loop iteration, in parallel; arithmetic in float64.
Forward per Gaussian: p = W m + t; J at (x, y) clamped to 1.3x the half field of view;
M = J W R(q) S; conic from M M^T + EPS I with det = |m0 x m1|^2 + EPS(|m0|^2 + |m1|^2) + EPS^2;
radius = ceil(3 sqrt(lambda_max)); colour = max(SH(dir) + 0.5, 0); opacity = sigmoid(logit).
Backward: the same chain read right to left (derivations in the comments of ``_backward_one``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from pipeline.splat.kernels import PRANGE_ONLY
from pipeline.splat.project import CLAMP_FOV, EPS_2D, MAX_VARIANCE_2D  # the rules have one source
from pipeline.splat.sh import C0, C1, C2, C3



@njit(cache=True, inline="always")
def _sh_basis(degree, x, y, z, out):
    """The (degree + 1)^2 real SH basis values at unit (x, y, z) into out[:16] (3DGS order)."""
    out[0] = C0
    if degree >= 1:
        out[1], out[2], out[3] = -C1 * y, C1 * z, -C1 * x
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out[4] = C2[0] * x * y
        out[5] = C2[1] * y * z
        out[6] = C2[2] * (2 * zz - xx - yy)
        out[7] = C2[3] * x * z
        out[8] = C2[4] * (xx - yy)
    if degree >= 3:
        out[9] = C3[0] * y * (3 * xx - yy)
        out[10] = C3[1] * x * y * z
        out[11] = C3[2] * y * (4 * zz - xx - yy)
        out[12] = C3[3] * z * (2 * zz - 3 * xx - 3 * yy)
        out[13] = C3[4] * x * (4 * zz - xx - yy)
        out[14] = C3[5] * z * (xx - yy)
        out[15] = C3[6] * x * (xx - 3 * yy)


@njit(cache=True, inline="always")
def _sh_basis_grad(degree, x, y, z, gx, gy, gz):
    """d basis_k / d(x, y, z) into gx, gy, gz [16] (the basis as a polynomial in x, y, z)."""
    for k in range(16):
        gx[k] = gy[k] = gz[k] = 0.0
    if degree >= 1:
        gy[1], gz[2], gx[3] = -C1, C1, -C1
    if degree >= 2:
        gx[4], gy[4] = C2[0] * y, C2[0] * x
        gy[5], gz[5] = C2[1] * z, C2[1] * y
        gx[6], gy[6], gz[6] = -2 * C2[2] * x, -2 * C2[2] * y, 4 * C2[2] * z
        gx[7], gz[7] = C2[3] * z, C2[3] * x
        gx[8], gy[8] = 2 * C2[4] * x, -2 * C2[4] * y
    if degree >= 3:
        xx, yy, zz = x * x, y * y, z * z
        gx[9], gy[9] = 6 * C3[0] * x * y, C3[0] * (3 * xx - 3 * yy)
        gx[10], gy[10], gz[10] = C3[1] * y * z, C3[1] * x * z, C3[1] * x * y
        gx[11], gy[11], gz[11] = -2 * C3[2] * x * y, C3[2] * (4 * zz - xx - 3 * yy), 8 * C3[2] * y * z
        gx[12], gy[12] = -6 * C3[3] * x * z, -6 * C3[3] * y * z
        gz[12] = C3[3] * (6 * zz - 3 * xx - 3 * yy)
        gx[13], gy[13], gz[13] = C3[4] * (4 * zz - 3 * xx - yy), -2 * C3[4] * x * y, 8 * C3[4] * x * z
        gx[14], gy[14], gz[14] = 2 * C3[5] * x * z, -2 * C3[5] * y * z, C3[5] * (xx - yy)
        gx[15], gy[15] = C3[6] * (3 * xx - 3 * yy), -6 * C3[6] * x * y


@njit(cache=True, inline="always")
def _rotation(q0, q1, q2, q3, rot):
    """rot [3, 3] from the unit quaternion (w, x, y, z)."""
    w, x, y, z = q0, q1, q2, q3
    rot[0, 0], rot[0, 1], rot[0, 2] = 1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)
    rot[1, 0], rot[1, 1], rot[1, 2] = 2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)
    rot[2, 0], rot[2, 1], rot[2, 2] = 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)


@njit(cache=True, inline="always")
def _unit_quat(quats, g, qn):
    """qn [4] = quats[g] / max(|quats[g]|, 1e-12); returns the norm used."""
    norm = math.sqrt(quats[g, 0] ** 2 + quats[g, 1] ** 2 + quats[g, 2] ** 2 + quats[g, 3] ** 2)
    norm = max(norm, 1e-12)
    for i in range(4):
        qn[i] = quats[g, i] / norm
    return norm


@njit(cache=True, error_model="numpy", inline="always")
def _geometry(g, means, log_scales, quats, view, intr, width, height, near, jac, rs, m, qn, rot):
    """The camera-space point and the 2D covariance factor M = J W R S of Gaussian g.

    Fills jac [2, 3], rs [3, 3] (= W R S), m [2, 3], qn [4], rot [3, 3]; returns
    (x, y, z, zz, in_front, clamped_x, clamped_y, rx, ry, finite, qnorm): zz = z in front of the
    near plane else 1; rx, ry the clamped x/zz, y/zz; finite False when M is too large (culled).
    """
    fx, fy = intr[0], intr[1]
    mx, my, mz = means[g, 0], means[g, 1], means[g, 2]
    x = view[0, 0] * mx + view[0, 1] * my + view[0, 2] * mz + view[0, 3]
    y = view[1, 0] * mx + view[1, 1] * my + view[1, 2] * mz + view[1, 3]
    z = view[2, 0] * mx + view[2, 1] * my + view[2, 2] * mz + view[2, 3]
    in_front = z > near
    zz = z if in_front else 1.0
    lim_x, lim_y = CLAMP_FOV * 0.5 * width / fx, CLAMP_FOV * 0.5 * height / fy
    rx, ry = x / zz, y / zz
    clamped_x, clamped_y = rx < -lim_x or rx > lim_x, ry < -lim_y or ry > lim_y
    rx, ry = min(max(rx, -lim_x), lim_x), min(max(ry, -lim_y), lim_y)
    tx, ty = zz * rx, zz * ry
    jac[0, 0], jac[0, 1], jac[0, 2] = fx / zz, 0.0, -fx * tx / (zz * zz)
    jac[1, 0], jac[1, 1], jac[1, 2] = 0.0, fy / zz, -fy * ty / (zz * zz)
    qnorm = _unit_quat(quats, g, qn)
    _rotation(qn[0], qn[1], qn[2], qn[3], rot)
    for i in range(3):
        for j in range(3):
            acc = 0.0
            for k in range(3):
                acc += view[i, k] * rot[k, j]
            rs[i, j] = acc * math.exp(log_scales[g, j])
    size = 0.0
    for i in range(2):
        for j in range(3):
            m[i, j] = jac[i, 0] * rs[0, j] + jac[i, 1] * rs[1, j] + jac[i, 2] * rs[2, j]
            size += m[i, j] * m[i, j]
    finite = math.isfinite(size) and size < MAX_VARIANCE_2D
    if not finite:
        for i in range(2):
            for j in range(3):
                m[i, j] = 0.0
    return x, y, z, zz, in_front, clamped_x, clamped_y, rx, ry, finite, qnorm


@njit(cache=True, inline="always")
def _conic_terms(m):
    """(a, b, c, det) of M M^T + EPS I: a, c the dilated diagonal, b the off-diagonal."""
    a0 = m[0, 0] ** 2 + m[0, 1] ** 2 + m[0, 2] ** 2
    c0 = m[1, 0] ** 2 + m[1, 1] ** 2 + m[1, 2] ** 2
    b = m[0, 0] * m[1, 0] + m[0, 1] * m[1, 1] + m[0, 2] * m[1, 2]
    u0 = m[0, 1] * m[1, 2] - m[0, 2] * m[1, 1]
    u1 = m[0, 2] * m[1, 0] - m[0, 0] * m[1, 2]
    u2 = m[0, 0] * m[1, 1] - m[0, 1] * m[1, 0]
    det = u0 * u0 + u1 * u1 + u2 * u2 + EPS_2D * (a0 + c0) + EPS_2D * EPS_2D
    return a0 + EPS_2D, b, c0 + EPS_2D, det


@njit(parallel=PRANGE_ONLY, cache=True, nogil=True)
def project_forward(means, log_scales, quats, logit_opacities, sh0, shn, view, intr, width, height,
                    sh_degree, near, workers, all_colors=True):
    """Per Gaussian: means2d [N, 2], conics [N, 3], depths [N], radii [N] int64, colors [N, 3],
    opacities [N] (float64). view [4, 4] world->camera; intr = (fx, fy, cx, cy).
    ``all_colors`` False: the SH colour and the conic only of the Gaussians with radius > 0, every
    culled one's left 0 (no tile lists a culled Gaussian, so nothing composited reads them; at 64
    px most of a real scene's Gaussians are culled in any one view and the degree-3 SH is ~40% of
    the projection), and a Gaussian behind the near plane or whose radius cannot reach the image
    (``_surely_off_image``) is culled before its covariance is built.

    The Gaussians are cut into ``workers`` contiguous blocks, one per parallel iteration; each
    block's body is a plain function with its own scratch arrays (numba hoists ``np.empty`` out of
    a ``prange`` body, which would share them between threads).
    """
    n, dtype = means.shape[0], means.dtype  # outputs in the parameters' dtype
    means2d, conics = np.empty((n, 2), dtype), np.empty((n, 3), dtype)
    depths, radii = np.empty(n, dtype), np.zeros(n, dtype=np.int64)
    colors, opacities = np.empty((n, 3), dtype), np.empty(n, dtype)
    stretch = _view_stretch(view)
    if workers == 1:  # no parallel region: no idle pool threads spinning beside the job
        _forward_block(0, n, means, log_scales, quats,
                       logit_opacities, sh0, shn, view, intr, width, height, sh_degree, near,
                       all_colors, stretch, means2d, conics, depths, radii, colors, opacities)
    else:
        for w in prange(workers):
            _forward_block(w * n // workers, (w + 1) * n // workers, means, log_scales, quats,
                           logit_opacities, sh0, shn, view, intr, width, height, sh_degree, near,
                           all_colors, stretch, means2d, conics, depths, radii, colors, opacities)
    return means2d, conics, depths, radii, colors, opacities


@njit(cache=True)
def _view_stretch(view):
    """An upper bound on |W v|^2 / |v|^2 for the view's 3 x 3 block W: the largest eigenvalue
    of W^T W is at most 1 + 3 max |W^T W - I| (about 1 for a rotation stored in float32), and at
    most the squared Frobenius norm."""
    frobenius, off = 0.0, 0.0
    for i in range(3):
        for j in range(3):
            frobenius += view[i, j] ** 2
            dot = view[0, i] * view[0, j] + view[1, i] * view[1, j] + view[2, i] * view[2, j]
            off = max(off, abs(dot - (1.0 if i == j else 0.0)))
    return min(1.0 + 3.0 * off + 1e-12, frobenius)  # |W|_2^2 <= 1 + |W^T W - I|_2


@njit(cache=True, error_model="numpy", inline="always")
def _surely_off_image(g, x, y, z, log_scales, intr, width, height, near, stretch):
    """True when Gaussian g (camera-space mean x, y, z) is surely culled: behind the near plane,
    or its radius (``_forward_block``'s rule) cannot reach the image. That radius is
    ceil(3 sqrt(mid + sqrt(max(mid^2 - det, 0.1)))) <= ceil(3 sqrt(a + c + 0.32)), and
    a + c = |J W R S|_F^2 + 2 EPS <= |J|_F^2 stretch s_max^2 + 2 EPS (R a rotation, s_max the
    largest scale); the bound is widened for rounding. NaN anywhere: False (the full rule)."""
    if not z > near:
        return not z != z  # behind (a NaN depth takes the full rule)
    fx, fy = intr[0], intr[1]
    lim_x, lim_y = CLAMP_FOV * 0.5 * width / fx, CLAMP_FOV * 0.5 * height / fy
    rx, ry = min(max(x / z, -lim_x), lim_x), min(max(y / z, -lim_y), lim_y)
    jac2 = (fx * fx + fy * fy + (fx * rx) ** 2 + (fy * ry) ** 2) / (z * z)
    s_max = math.exp(max(log_scales[g, 0], log_scales[g, 1], log_scales[g, 2]))
    bound = jac2 * stretch * s_max * s_max + 2.0 * EPS_2D + 0.32
    reach = 3.0 * math.sqrt(bound * (1.0 + 1e-6)) + 2.0
    u, v = fx * x / z + intr[2], fy * y / z + intr[3]
    return u + reach <= 0.0 or u - reach >= width or v + reach <= 0.0 or v - reach >= height


@njit(cache=True, error_model="numpy")
def _forward_block(lo, hi, means, log_scales, quats, logit_opacities, sh0, shn, view, intr, width,
                   height, sh_degree, near, all_colors, stretch, means2d, conics, depths, radii,
                   colors, opacities):
    bases = (sh_degree + 1) ** 2
    jac, rs, m = np.empty((2, 3)), np.empty((3, 3)), np.empty((2, 3))
    qn, rot, basis, d = np.empty(4), np.empty((3, 3)), np.empty(16), np.empty(3)
    for g in range(lo, hi):
        if not all_colors:  # a surely culled Gaussian: the outputs the full rule gives it
            mx, my, mz = means[g, 0], means[g, 1], means[g, 2]
            x = view[0, 0] * mx + view[0, 1] * my + view[0, 2] * mz + view[0, 3]
            y = view[1, 0] * mx + view[1, 1] * my + view[1, 2] * mz + view[1, 3]
            z = view[2, 0] * mx + view[2, 1] * my + view[2, 2] * mz + view[2, 3]
            if _surely_off_image(g, x, y, z, log_scales, intr, width, height, near, stretch):
                zz = z if z > near else 1.0
                means2d[g, 0], means2d[g, 1] = intr[0] * x / zz + intr[2], intr[1] * y / zz + intr[3]
                depths[g] = z
                opacities[g] = 1.0 / (1.0 + math.exp(-logit_opacities[g]))
                for i in range(3):
                    conics[g, i] = colors[g, i] = 0.0
                continue
        x, y, z, zz, in_front, _, _, _, _, finite, _ = _geometry(
            g, means, log_scales, quats, view, intr, width, height, near, jac, rs, m, qn, rot)
        a, b, c, det = _conic_terms(m)
        conics[g, 0], conics[g, 1], conics[g, 2] = c / det, -b / det, a / det
        u, v = intr[0] * x / zz + intr[2], intr[1] * y / zz + intr[3]
        means2d[g, 0], means2d[g, 1] = u, v
        depths[g] = z
        mid = 0.5 * (a + c)
        radius = math.ceil(3.0 * math.sqrt(mid + math.sqrt(max(mid * mid - det, 0.1))))
        on_image = u + radius > 0 and u - radius < width and v + radius > 0 and v - radius < height
        if in_front and on_image and finite:
            radii[g] = int(radius)
        opacities[g] = 1.0 / (1.0 + math.exp(-logit_opacities[g]))
        if not all_colors and radii[g] == 0:
            for i in range(3):
                conics[g, i] = colors[g, i] = 0.0
            continue
        # view direction camera centre -> Gaussian: m + W^T t, normalised
        for i in range(3):
            d[i] = means[g, i] + view[0, i] * view[0, 3] + view[1, i] * view[1, 3] + view[2, i] * view[2, 3]
        dn = max(math.sqrt(d[0] ** 2 + d[1] ** 2 + d[2] ** 2), 1e-12)
        _sh_basis(sh_degree, d[0] / dn, d[1] / dn, d[2] / dn, basis)
        for ch in range(3):
            acc = basis[0] * sh0[g, 0, ch]
            for k in range(1, bases):
                acc += basis[k] * shn[g, k - 1, ch]
            colors[g, ch] = max(acc + 0.5, 0.0)


@njit(parallel=PRANGE_ONLY, cache=True, nogil=True)
def project_backward(means, log_scales, quats, logit_opacities, sh0, shn, view, intr, width,
                     height, sh_degree, near, g_means2d, g_conics, g_depths, g_colors, g_opac,
                     workers):
    """Vector-Jacobian product of ``project_forward``: gradients of means [N, 3], log_scales
    [N, 3], quats [N, 4], logit_opacities [N], sh0 [N, 1, 3], shN [N, K-1, 3] (float64)."""
    n, dtype = means.shape[0], means.dtype  # gradients in the parameters' dtype
    d_means, d_ls, d_q = np.empty((n, 3), dtype), np.empty((n, 3), dtype), np.empty((n, 4), dtype)
    d_logit = np.empty(n, dtype)
    d_sh0, d_shn = np.empty(sh0.shape, dtype), np.empty(shn.shape, dtype)  # zeroed per Gaussian
    if workers == 1:  # no parallel region: no idle pool threads spinning beside the job
        _backward_block(0, n, means, log_scales, quats,
                        logit_opacities, sh0, shn, view, intr, width, height, sh_degree, near,
                        g_means2d, g_conics, g_depths, g_colors, g_opac, d_means, d_ls, d_q,
                        d_logit, d_sh0, d_shn)
    else:
        for w in prange(workers):
            _backward_block(w * n // workers, (w + 1) * n // workers, means, log_scales, quats,
                            logit_opacities, sh0, shn, view, intr, width, height, sh_degree, near,
                            g_means2d, g_conics, g_depths, g_colors, g_opac, d_means, d_ls, d_q,
                            d_logit, d_sh0, d_shn)
    return d_means, d_ls, d_q, d_logit, d_sh0, d_shn


@njit(cache=True, error_model="numpy")
def _direction(g, means, view, d):
    """Fill d with the view direction m + W^T t (camera centre -> Gaussian); returns |d|."""
    for i in range(3):
        d[i] = means[g, i] + view[0, i] * view[0, 3] + view[1, i] * view[1, 3] + view[2, i] * view[2, 3]
    return max(math.sqrt(d[0] ** 2 + d[1] ** 2 + d[2] ** 2), 1e-12)


@njit(cache=True, error_model="numpy")
def _colour_is_live(g, sh0, shn, bases, basis, ch):
    """True when channel ch's colour is not clamped at 0 (SH + 0.5 >= 0)."""
    acc = basis[0] * sh0[g, 0, ch]
    for k in range(1, bases):
        acc += basis[k] * shn[g, k - 1, ch]
    return acc + 0.5 >= 0.0


@njit(cache=True, error_model="numpy", inline="always")
def _chain(g, k0, k1, k2, gu, gv, g_depth, gdx, gdy, gdz, log_scales, view, intr, geo, jac, rs, m,
           qn, rot, unit, dn, gm, gj, grs, gr, out):
    """Gradients of means, log_scales, quats (out[0:3], [3:6], [6:10], overwritten) from upstream
    gradients of the conic (k0, k1, k2), of means2d (gu, gv), the depth and the unit view
    direction (gdx, gdy, gdz). ``geo`` = ``_geometry``'s scalars, the arrays its outputs."""
    x, y, z, zz, in_front, cl_x, cl_y, rx, ry, finite, qnorm = geo
    fx, fy = intr[0], intr[1]
    for i in range(10):
        out[i] = 0.0
    # through the normalisation u = d / |d| (d = m + W^T t): (g - u (u . g)) / |d|
    dot = gdx * unit[0] + gdy * unit[1] + gdz * unit[2]
    out[0] = (gdx - unit[0] * dot) / dn
    out[1] = (gdy - unit[1] * dot) / dn
    out[2] = (gdz - unit[2] * dot) / dn
    # means2d: u = fx x / zz + cx, v = fy y / zz + cy; depth = z (unclamped)
    g_x, g_y = gu * fx / zz, gv * fy / zz
    g_zz = -gu * fx * x / (zz * zz) - gv * fy * y / (zz * zz)
    g_z = g_depth
    if finite and (k0 != 0.0 or k1 != 0.0 or k2 != 0.0):
        # conic = (c, -b, a) / det with a = a0 + EPS, c = c0 + EPS and (Lagrange)
        # det = a0 c0 - b^2 + EPS (a0 + c0) + EPS^2, so d det = c d a0 + a d c0 - 2 b d b
        a, b, c, det = _conic_terms(m)
        g_det = -(k0 * c - k1 * b + k2 * a) / (det * det)
        g_a0 = k2 / det + g_det * c
        g_c0 = k0 / det + g_det * a
        g_b = -k1 / det - 2.0 * b * g_det
        for j in range(3):  # a0 = |m0|^2, c0 = |m1|^2, b = m0 . m1
            gm[0, j] = 2.0 * g_a0 * m[0, j] + g_b * m[1, j]
            gm[1, j] = 2.0 * g_c0 * m[1, j] + g_b * m[0, j]
        # M = J RS: dJ = dM RS^T, dRS = J^T dM
        for i in range(2):
            for j in range(3):
                gj[i, j] = gm[i, 0] * rs[j, 0] + gm[i, 1] * rs[j, 1] + gm[i, 2] * rs[j, 2]
        for i in range(3):
            for j in range(3):
                grs[i, j] = jac[0, i] * gm[0, j] + jac[1, i] * gm[1, j]
        # J = [[fx/zz, 0, -fx tx/zz^2], [0, fy/zz, -fy ty/zz^2]], tx = zz * clamp(x / zz)
        tx, ty = zz * rx, zz * ry
        zz2, zz3 = zz * zz, zz * zz * zz
        g_zz += -gj[0, 0] * fx / zz2 - gj[1, 1] * fy / zz2
        g_zz += gj[0, 2] * 2.0 * fx * tx / zz3 + gj[1, 2] * 2.0 * fy * ty / zz3
        g_tx, g_ty = -gj[0, 2] * fx / zz2, -gj[1, 2] * fy / zz2
        if cl_x:  # tx = zz * lim: depends on zz only
            g_zz += g_tx * rx
        else:  # tx = x
            g_x += g_tx
        if cl_y:
            g_zz += g_ty * ry
        else:
            g_y += g_ty
        # RS = W R S: d(R S) = W^T dRS; (R S)_ij = R_ij s_j
        for j in range(3):
            s = math.exp(log_scales[g, j])
            gs = 0.0
            for i in range(3):
                gl = view[0, i] * grs[0, j] + view[1, i] * grs[1, j] + view[2, i] * grs[2, j]
                gr[i, j] = gl * s
                gs += gl * rot[i, j]
            out[3 + j] = gs * s
        # rotation of the unit quaternion (w, x, y, z)
        w, qx, qy, qz = qn[0], qn[1], qn[2], qn[3]
        gw = 2 * (-qz * gr[0, 1] + qy * gr[0, 2] + qz * gr[1, 0] - qx * gr[1, 2]
                  - qy * gr[2, 0] + qx * gr[2, 1])
        gx = 2 * (qy * gr[0, 1] + qz * gr[0, 2] + qy * gr[1, 0] - 2 * qx * gr[1, 1]
                  - w * gr[1, 2] + qz * gr[2, 0] + w * gr[2, 1] - 2 * qx * gr[2, 2])
        gy = 2 * (-2 * qy * gr[0, 0] + qx * gr[0, 1] + w * gr[0, 2] + qx * gr[1, 0]
                  + qz * gr[1, 2] - w * gr[2, 0] + qz * gr[2, 1] - 2 * qy * gr[2, 2])
        gz = 2 * (-2 * qz * gr[0, 0] - w * gr[0, 1] + qx * gr[0, 2] + w * gr[1, 0]
                  - 2 * qz * gr[1, 1] + qy * gr[1, 2] + qx * gr[2, 0] + qy * gr[2, 1])
        dot = gw * w + gx * qx + gy * qy + gz * qz  # through q / |q|
        out[6] = (gw - w * dot) / qnorm
        out[7] = (gx - qx * dot) / qnorm
        out[8] = (gy - qy * dot) / qnorm
        out[9] = (gz - qz * dot) / qnorm
    if in_front:  # zz = z in front of the near plane, else the constant 1
        g_z += g_zz
    for i in range(3):  # p = W m + t
        out[i] += view[0, i] * g_x + view[1, i] * g_y + view[2, i] * g_z


@njit(cache=True, nogil=True)
def chain_scratch():
    """Per-block scratch of the backward chain: jac, rs, m, qn, rot, d, unit, basis, bx, by, bz
    (SH basis and its gradient), gm, gj, grs, gr (the chain's intermediate gradients)."""
    return (np.empty((2, 3)), np.empty((3, 3)), np.empty((2, 3)), np.empty(4), np.empty((3, 3)),
            np.empty(3), np.empty(3), np.empty(16), np.empty(16), np.empty(16), np.empty(16),
            np.empty((2, 3)), np.empty((2, 3)), np.empty((3, 3)), np.empty((3, 3)))


@njit(cache=True, inline="always")
def _no_upstream(g, g_means2d, g_conics, g_depths, g_colors, g_opac):
    """True when every upstream gradient of Gaussian g is zero (culled, or reached no pixel
    that the loss sees): the backward is linear in them, so its gradients are exactly zero."""
    return (g_means2d[g, 0] == 0.0 and g_means2d[g, 1] == 0.0 and g_conics[g, 0] == 0.0
            and g_conics[g, 1] == 0.0 and g_conics[g, 2] == 0.0 and g_depths[g] == 0.0
            and g_colors[g, 0] == 0.0 and g_colors[g, 1] == 0.0 and g_colors[g, 2] == 0.0
            and g_opac[g] == 0.0)


@njit(cache=True, inline="always")
def _zero_gradients(g, d_means, d_ls, d_q, d_logit, d_sh0, d_shn):
    for i in range(3):
        d_means[g, i] = 0.0
        d_ls[g, i] = 0.0
        d_sh0[g, 0, i] = 0.0
    for i in range(4):
        d_q[g, i] = 0.0
    d_logit[g] = 0.0
    for k in range(d_shn.shape[1]):
        for i in range(3):
            d_shn[g, k, i] = 0.0


@njit(cache=True, error_model="numpy")
def _backward_block(lo, hi, means, log_scales, quats, logit_opacities, sh0, shn, view, intr, width,
                    height, sh_degree, near, g_means2d, g_conics, g_depths, g_colors, g_opac,
                    d_means, d_ls, d_q, d_logit, d_sh0, d_shn):
    bases = (sh_degree + 1) ** 2
    jac, rs, m, qn, rot, d, unit, basis, bx, by, bz, gm, gj, grs, gr = chain_scratch()
    out = np.empty(10)
    for g in range(lo, hi):
        if _no_upstream(g, g_means2d, g_conics, g_depths, g_colors, g_opac):
            _zero_gradients(g, d_means, d_ls, d_q, d_logit, d_sh0, d_shn)
            continue
        geo = _geometry(g, means, log_scales, quats, view, intr, width, height, near, jac, rs, m,
                        qn, rot)
        o = 1.0 / (1.0 + math.exp(-logit_opacities[g]))  # opacity = sigmoid(logit)
        d_logit[g] = g_opac[g] * o * (1.0 - o)
        # colour_c = max(sum_k basis_k sh_kc + 0.5, 0): SH coefficients and the view direction
        dn = _direction(g, means, view, d)
        for i in range(3):
            unit[i] = d[i] / dn
        _sh_basis(sh_degree, unit[0], unit[1], unit[2], basis)
        _sh_basis_grad(sh_degree, unit[0], unit[1], unit[2], bx, by, bz)
        gdx, gdy, gdz = 0.0, 0.0, 0.0
        d_sh0[g] = 0.0
        d_shn[g] = 0.0
        for ch in range(3):
            if not _colour_is_live(g, sh0, shn, bases, basis, ch):
                continue
            gc = g_colors[g, ch]
            d_sh0[g, 0, ch] = basis[0] * gc
            for k in range(1, bases):
                d_shn[g, k - 1, ch] = basis[k] * gc
                coeff = gc * shn[g, k - 1, ch]
                gdx += coeff * bx[k]
                gdy += coeff * by[k]
                gdz += coeff * bz[k]
        _chain(g, g_conics[g, 0], g_conics[g, 1], g_conics[g, 2], g_means2d[g, 0], g_means2d[g, 1],
               g_depths[g], gdx, gdy, gdz, log_scales, view, intr, geo, jac, rs, m, qn, rot, unit,
               dn, gm, gj, grs, gr, out)
        for i in range(3):
            d_means[g, i] = out[i]
            d_ls[g, i] = out[3 + i]
        for i in range(4):
            d_q[g, i] = out[6 + i]


@njit(cache=True, error_model="numpy")
def jacobian_one(g, means, log_scales, quats, logit_opacities, sh0, shn, view, intr, width, height,
                 sh_degree, near, scratch, geometry, sh_slope):
    """Gaussian g's feature Jacobian: fills geometry [8, 10] (every entry) and sh_slope [K, 3]
    (live entries only: the caller zeroes it), returns d opacity / d logit. ``scratch`` is
    ``chain_scratch()``."""
    bases = (sh_degree + 1) ** 2
    jac, rs, m, qn, rot, d, unit, basis, bx, by, bz, gm, gj, grs, gr = scratch
    geo = _geometry(g, means, log_scales, quats, view, intr, width, height, near, jac, rs, m, qn, rot)
    o = 1.0 / (1.0 + math.exp(-logit_opacities[g]))
    dn = _direction(g, means, view, d)
    for i in range(3):
        unit[i] = d[i] / dn
    _sh_basis(sh_degree, unit[0], unit[1], unit[2], basis)
    _sh_basis_grad(sh_degree, unit[0], unit[1], unit[2], bx, by, bz)
    # rows u, v, conic a, b, c: one-hot upstream gradients
    _chain(g, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, log_scales, view, intr, geo, jac, rs,
           m, qn, rot, unit, dn, gm, gj, grs, gr, geometry[0])
    _chain(g, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, log_scales, view, intr, geo, jac, rs,
           m, qn, rot, unit, dn, gm, gj, grs, gr, geometry[1])
    for r in range(3):
        k0, k1, k2 = 1.0 if r == 0 else 0.0, 1.0 if r == 1 else 0.0, 1.0 if r == 2 else 0.0
        _chain(g, k0, k1, k2, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, log_scales, view, intr, geo, jac,
               rs, m, qn, rot, unit, dn, gm, gj, grs, gr, geometry[2 + r])
    # colour rows: the view direction moves with the mean; the SH slopes are the basis
    for ch in range(3):
        gdx, gdy, gdz = 0.0, 0.0, 0.0
        if _colour_is_live(g, sh0, shn, bases, basis, ch):
            for k in range(1, bases):
                gdx += shn[g, k - 1, ch] * bx[k]
                gdy += shn[g, k - 1, ch] * by[k]
                gdz += shn[g, k - 1, ch] * bz[k]
        _chain(g, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, gdx, gdy, gdz, log_scales, view, intr, geo, jac,
               rs, m, qn, rot, unit, dn, gm, gj, grs, gr, geometry[5 + ch])
        acc = basis[0] * sh0[g, 0, ch]
        for k in range(1, bases):
            acc += basis[k] * shn[g, k - 1, ch]
        if acc + 0.5 > 0.0:  # the colour is strictly positive: not clamped
            for k in range(bases):
                sh_slope[k, ch] = basis[k]
    return o * (1.0 - o)


@njit(cache=True, error_model="numpy")
def _jacobian_block(lo, hi, means, log_scales, quats, logit_opacities, sh0, shn, view, intr, width,
                    height, sh_degree, near, geometry, sh_slope, opacity_slope):
    scratch = chain_scratch()
    for g in range(lo, hi):
        opacity_slope[g] = jacobian_one(g, means, log_scales, quats, logit_opacities, sh0, shn,
                                        view, intr, width, height, sh_degree, near, scratch,
                                        geometry[g], sh_slope[g])


@njit(parallel=PRANGE_ONLY, cache=True, nogil=True)
def feature_jacobian(means, log_scales, quats, logit_opacities, sh0, shn, view, intr, width, height,
                     sh_degree, near, workers):
    """The Jacobian of a view's 2D features w.r.t. the raw parameters, per Gaussian:
    geometry [N, 8, 10]: rows (u, v, conic a, b, c, r, g, b), columns (means 3, log_scales 3,
    quats 4); sh_slope [N, K, 3] = d colour_c / d sh_kc (0 beyond the active degree and where the
    colour is clamped); opacity_slope [N] = d opacity / d logit. Float64."""
    n = means.shape[0]
    geometry = np.zeros((n, 8, 10))
    sh_slope = np.zeros((n, shn.shape[1] + 1, 3))
    opacity_slope = np.empty(n)
    if workers == 1:  # no parallel region: no idle pool threads spinning beside the job
        _jacobian_block(0, n, means, log_scales, quats,
                        logit_opacities, sh0, shn, view, intr, width, height, sh_degree, near,
                        geometry, sh_slope, opacity_slope)
    else:
        for w in prange(workers):
            _jacobian_block(w * n // workers, (w + 1) * n // workers, means, log_scales, quats,
                            logit_opacities, sh0, shn, view, intr, width, height, sh_degree, near,
                            geometry, sh_slope, opacity_slope)
    return geometry, sh_slope, opacity_slope
