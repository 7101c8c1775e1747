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

from pipeline.splat.gaussians import Gaussians, covariances
from pipeline.splat.sh import eval_sh

EPS_2D = 0.3


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


def project(gaussians: Gaussians, viewmat: Tensor, K: Tensor, width: int, height: int,
            sh_degree: int | None = None, near: float = 0.01) -> Projection:
    """Project ``gaussians`` with world->camera ``viewmat`` [4, 4] and intrinsics ``K`` [3, 3]."""
    sh_degree = gaussians.sh_degree if sh_degree is None else sh_degree
    if sh_degree > gaussians.sh_degree:
        raise ValueError(f"sh_degree {sh_degree} exceeds the stored degree {gaussians.sh_degree}")
    rot, trans = viewmat[:3, :3], viewmat[:3, 3]
    p_cam = gaussians.means @ rot.T + trans  # [N, 3]
    x, y, z = p_cam.unbind(-1)
    in_front = z > near
    z = torch.where(in_front, z, torch.ones_like(z))  # keeps culled rows finite (and their grads)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]

    lim_x = 1.3 * 0.5 * width / fx
    lim_y = 1.3 * 0.5 * height / fy
    tx = z * torch.clamp(x / z, -lim_x, lim_x)
    ty = z * torch.clamp(y / z, -lim_y, lim_y)
    zero = torch.zeros_like(z)
    jac = torch.stack([fx / z, zero, -fx * tx / (z * z),
                       zero, fy / z, -fy * ty / (z * z)], dim=-1).reshape(-1, 2, 3)  # [N, 2, 3]
    cov_cam = rot @ covariances(gaussians.log_scales, gaussians.quats) @ rot.T  # [N, 3, 3]
    cov2d = jac @ cov_cam @ jac.transpose(1, 2)  # [N, 2, 2]
    a = cov2d[:, 0, 0] + EPS_2D
    b = cov2d[:, 0, 1]
    c = cov2d[:, 1, 1] + EPS_2D
    det = a * c - b * b  # >= 0.09 since cov2d is PSD
    conics = torch.stack([c / det, -b / det, a / det], dim=-1)

    means2d = torch.stack([fx * x / z + cx, fy * y / z + cy], dim=-1)
    with torch.no_grad():
        mid = 0.5 * (a + c)
        lam = mid + torch.sqrt(torch.clamp(mid * mid - det, min=0.1))
        radius = torch.ceil(3 * torch.sqrt(lam))
        u, v = means2d.unbind(-1)
        on_image = (u + radius > 0) & (u - radius < width) & (v + radius > 0) & (v - radius < height)
        radii = torch.where(in_front & on_image, radius, torch.zeros_like(radius)).long()

    dirs = view_directions(gaussians.means, viewmat)
    colors = torch.clamp_min(eval_sh(sh_degree, gaussians.sh, dirs) + 0.5, 0.0)
    return Projection(means2d, conics, p_cam[:, 2], radii, colors, gaussians.opacities)
