"""EWA projection of 3D Gaussians into one pinhole camera, with the 3DGS rules.

Rules (Kerbl et al. 2023): Gaussians at or behind the near plane are culled; the 2D covariance is
J W Sigma W^T J^T + 0.3 I (the EWA low-pass dilation), with J evaluated at a camera-space point
whose x/z and y/z are clamped to 1.3x the half field of view; radius = ceil(3 sqrt(largest
eigenvalue)); colour from SH at the direction camera centre -> Gaussian, + 0.5, clamped at 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from pipeline.splat.gaussians import Gaussians, scaled_rotations
from pipeline.splat.sh import eval_sh

EPS_2D = 0.3
# The projection Jacobian is taken at x/z, y/z clamped to this multiple of the half field of view
# (3DGS's rule: Gaussians far off-screen do not get huge screen-space footprints).
CLAMP_FOV = 1.3
# Largest 2D variance (px^2) a Gaussian may have and still be drawn: a standard deviation of about
# 3e7 px. Beyond it the float32 products of the conic's backward could overflow; such Gaussians
# (only ever seen right at the near plane) are culled like Gaussians behind the camera.
MAX_VARIANCE_2D = 1e15


@dataclass
class Projection:
    """Per-Gaussian 2D quantities for one camera (N Gaussians).

    means2d [N, 2] pixel coordinates (pixel centres at +0.5); conics [N, 3] = (a, b, c) of the
    inverse 2D covariance [[a, b], [b, c]]; depths [N] camera z; radii [N] int64 pixel radius,
    0 for culled Gaussians; colors [N, 3]; opacities [N].
    """

    means2d: Tensor
    conics: Tensor
    depths: Tensor
    radii: Tensor
    colors: Tensor
    opacities: Tensor


def view_directions(means: Tensor, viewmat: Tensor) -> Tensor:
    """Unit directions camera centre -> Gaussian [N, 3] (where the SH colour is evaluated)."""
    rot, trans = viewmat[:3, :3], viewmat[:3, 3]
    return torch.nn.functional.normalize(means + rot.T @ trans, dim=-1)


def conic_2d(jac: Tensor, rs_cam: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """The dilated 2D covariance J (R S)(R S)^T J^T + EPS_2D I and its inverse, without cancellation.

    jac [N, 2, 3] the projection Jacobian, rs_cam [N, 3, 3] = W R S (the camera-frame square root
    of the 3D covariance). With M = J W R S [N, 2, 3] and rows m0, m1, the covariance is M M^T and
    its determinant is |m0 x m1|^2 (Lagrange's identity) + EPS (|m0|^2 + |m1|^2) + EPS^2: a sum of
    non-negative terms, so det >= EPS^2 holds in floating point too. (The textbook a c - b^2 cancels
    catastrophically in float32 for the huge covariances of Gaussians at the near plane and gave 0
    or negative determinants: infinite or indefinite conics, NaN renders.)
    Returns conics [N, 3] = (a, b, c) of the inverse, the dilated diagonal a, c [N], det [N] and
    ``finite`` [N] bool: False for Gaussians too large to draw (their conics are set to safe values).
    """
    m = jac @ rs_cam  # [N, 2, 3]
    with torch.no_grad():
        size = m.square().sum(dim=(1, 2))
        finite = torch.isfinite(size) & (size < MAX_VARIANCE_2D)
    m = torch.where(finite[:, None, None], m, torch.zeros_like(m))  # culled rows: finite, no gradient
    m0, m1 = m.unbind(1)
    a0, c0, b = (m0 * m0).sum(-1), (m1 * m1).sum(-1), (m0 * m1).sum(-1)
    det = torch.linalg.cross(m0, m1).square().sum(-1) + EPS_2D * (a0 + c0) + EPS_2D ** 2
    a, c = a0 + EPS_2D, c0 + EPS_2D
    conics = torch.stack([c / det, -b / det, a / det], dim=-1)
    return conics, a, c, det, finite


def active_sh_degree(gaussians: Gaussians, sh_degree: int | None) -> int:
    """The SH degree to evaluate: ``sh_degree``, or the stored one when None; never above it."""
    sh_degree = gaussians.sh_degree if sh_degree is None else sh_degree
    if sh_degree > gaussians.sh_degree:
        raise ValueError(f"sh_degree {sh_degree} exceeds the stored degree {gaussians.sh_degree}")
    return sh_degree


def project(gaussians: Gaussians, viewmat: Tensor, K: Tensor, width: int, height: int,
            sh_degree: int | None = None, near: float = 0.01) -> Projection:
    """Project ``gaussians`` with world->camera ``viewmat`` [4, 4] and intrinsics ``K`` [3, 3]."""
    sh_degree = active_sh_degree(gaussians, sh_degree)
    rot, trans = viewmat[:3, :3], viewmat[:3, 3]
    p_cam = gaussians.means @ rot.T + trans  # [N, 3]
    x, y, z = p_cam.unbind(-1)
    in_front = z > near
    z = torch.where(in_front, z, torch.ones_like(z))  # keeps culled rows finite (and their grads)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]

    lim_x = CLAMP_FOV * 0.5 * width / fx
    lim_y = CLAMP_FOV * 0.5 * height / fy
    tx = z * torch.clamp(x / z, -lim_x, lim_x)
    ty = z * torch.clamp(y / z, -lim_y, lim_y)
    zero = torch.zeros_like(z)
    jac = torch.stack([fx / z, zero, -fx * tx / (z * z),
                       zero, fy / z, -fy * ty / (z * z)], dim=-1).reshape(-1, 2, 3)  # [N, 2, 3]
    rs_cam = rot @ scaled_rotations(gaussians.log_scales, gaussians.quats)  # [N, 3, 3]
    conics, a, c, det, finite = conic_2d(jac, rs_cam)

    means2d = torch.stack([fx * x / z + cx, fy * y / z + cy], dim=-1)
    with torch.no_grad():
        mid = 0.5 * (a + c)
        lam = mid + torch.sqrt(torch.clamp(mid * mid - det, min=0.1))
        radius = torch.ceil(3 * torch.sqrt(lam))
        u, v = means2d.unbind(-1)
        on_image = (u + radius > 0) & (u - radius < width) & (v + radius > 0) & (v - radius < height)
        radii = torch.where(in_front & on_image & finite, radius, torch.zeros_like(radius)).long()

    dirs = view_directions(gaussians.means, viewmat)
    colors = torch.clamp_min(eval_sh(sh_degree, gaussians.sh, dirs) + 0.5, 0.0)
    return Projection(means2d, conics, p_cam[:, 2], radii, colors, gaussians.opacities)
