"""Real spherical harmonics up to degree 3, in the order and with the constants of 3DGS."""

from __future__ import annotations

from torch import Tensor

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
      0.5462742152960396)
C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
      -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


def sh_basis(degree: int, dirs: Tensor) -> list[Tensor]:
    """The (degree+1)^2 SH basis functions at unit directions ``dirs`` [..., 3], each [...]."""
    x, y, z = dirs.unbind(-1)
    basis = [x.new_full(x.shape, C0)]
    if degree >= 1:
        basis += [-C1 * y, C1 * z, -C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        basis += [C2[0] * xy, C2[1] * yz, C2[2] * (2 * zz - xx - yy), C2[3] * xz, C2[4] * (xx - yy)]
    if degree >= 3:
        basis += [
            C3[0] * y * (3 * xx - yy),
            C3[1] * xy * z,
            C3[2] * y * (4 * zz - xx - yy),
            C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            C3[4] * x * (4 * zz - xx - yy),
            C3[5] * z * (xx - yy),
            C3[6] * x * (xx - 3 * yy),
        ]
    return basis


def eval_sh(degree: int, coeffs: Tensor, dirs: Tensor) -> Tensor:
    """Evaluate SH colour.

    degree: active degree (<= the stored one); coeffs: [N, K, 3] with K >= (degree+1)^2;
    dirs: [N, 3] unit view directions (camera -> Gaussian). Returns [N, 3] (before the +0.5 offset).
    """
    if not 0 <= degree <= 3:
        raise ValueError(f"sh degree must be in 0..3, got {degree}")
    if coeffs.shape[1] < (degree + 1) ** 2:
        raise ValueError(f"coeffs has {coeffs.shape[1]} bases, degree {degree} needs "
                         f"{(degree + 1) ** 2}")
    result = None
    for i, b in enumerate(sh_basis(degree, dirs)):
        term = b[:, None] * coeffs[:, i, :]
        result = term if result is None else result + term
    assert result is not None  # degree >= 0: one basis function at least
    return result
