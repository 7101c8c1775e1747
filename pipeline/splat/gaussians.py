"""3D Gaussians as raw (unconstrained) parameters.

Storage and activations:
- ``means``            [N, 3]  world positions.
- ``log_scales``       [N, 3]  scales = exp(log_scales).
- ``quats``            [N, 4]  rotation quaternion in (w, x, y, z) order, not necessarily unit;
                              normalised before use.
- ``logit_opacities``  [N]     opacities = sigmoid(logit_opacities).
- ``sh0``              [N, 1, 3]  degree-0 spherical-harmonics coefficients (the DC colour term).
- ``shN``              [N, K-1, 3] higher-order coefficients, K = (degree + 1)^2, degree in 0..3.
Colour = clamp_min(SH(view direction) + 0.5, 0) as in 3DGS.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import torch
from torch import Tensor

PARAM_NAMES = ("means", "log_scales", "quats", "logit_opacities", "sh0", "shN")
SH_C0 = 0.28209479177387814


def num_sh_bases(degree: int) -> int:
    return (degree + 1) ** 2


@dataclass
class Gaussians:
    means: Tensor
    log_scales: Tensor
    quats: Tensor
    logit_opacities: Tensor
    sh0: Tensor
    shN: Tensor

    def __post_init__(self) -> None:
        self.validate()

    @classmethod
    def unchecked(cls, **params: Tensor) -> "Gaussians":
        """The same record without ``validate`` (its reductions cost ~0.3 ms): for a hot loop
        over parameters it has validated itself (the trainer's step). Anything else constructs."""
        gaussians = cls.__new__(cls)
        for field in fields(cls):
            setattr(gaussians, field.name, params[field.name])
        return gaussians

    # -- checks ---------------------------------------------------------------------------
    def validate(self) -> None:
        """Raise ValueError naming the field on wrong shapes or non-finite values."""
        n = self.means.shape[0] if self.means.ndim == 2 else -1
        expected = {"means": (n, 3), "log_scales": (n, 3), "quats": (n, 4),
                    "logit_opacities": (n,), "sh0": (n, 1, 3)}
        if self.means.ndim != 2 or self.means.shape[1] != 3:
            raise ValueError(f"means must be [N, 3], got {tuple(self.means.shape)}")
        for name, shape in expected.items():
            value = getattr(self, name)
            if tuple(value.shape) != shape:
                raise ValueError(f"{name} must have shape {list(shape)}, got {list(value.shape)}")
        k = self.shN.shape[1] + 1 if self.shN.ndim == 3 else -1
        if self.shN.ndim != 3 or self.shN.shape[0] != n or self.shN.shape[2] != 3 or \
                k not in (1, 4, 9, 16):
            raise ValueError(f"shN must be [N, K-1, 3] with K in (1, 4, 9, 16), got "
                             f"{list(self.shN.shape)}")
        if not all_finite([getattr(self, name) for name in PARAM_NAMES]):
            for name in PARAM_NAMES:
                if not bool(torch.isfinite(getattr(self, name)).all()):
                    raise ValueError(f"{name} contains NaN or inf")
        if bool((self.quats.detach().norm(dim=-1) == 0).any()):
            raise ValueError("quats contains a zero quaternion")

    # -- sizes ----------------------------------------------------------------------------
    def __len__(self) -> int:
        return self.means.shape[0]

    @property
    def sh_degree(self) -> int:
        return int(round((self.shN.shape[1] + 1) ** 0.5)) - 1

    # -- activated values -----------------------------------------------------------------
    @property
    def scales(self) -> Tensor:
        return torch.exp(self.log_scales)

    @property
    def opacities(self) -> Tensor:
        return torch.sigmoid(self.logit_opacities)

    @property
    def sh(self) -> Tensor:
        """All SH coefficients, [N, K, 3]."""
        return torch.cat([self.sh0, self.shN], dim=1)

    # -- containers -----------------------------------------------------------------------
    def params(self) -> dict[str, Tensor]:
        return {name: getattr(self, name) for name in PARAM_NAMES}

    def replace(self, **changes: Tensor) -> "Gaussians":
        return replace(self, **changes)

    def detach(self) -> "Gaussians":
        return Gaussians(**{k: v.detach() for k, v in self.params().items()})

    def clone(self) -> "Gaussians":
        return Gaussians(**{k: v.detach().clone() for k, v in self.params().items()})

    def requires_grad_(self, flag: bool = True) -> "Gaussians":
        for value in self.params().values():
            value.requires_grad_(flag)
        return self

    def to(self, device=None, dtype=None) -> "Gaussians":
        return Gaussians(**{k: v.to(device=device, dtype=dtype) for k, v in self.params().items()})

    def at_sh_degree(self, degree: int) -> "Gaussians":
        """The same Gaussians with the SH coefficients above ``degree`` dropped: the model that
        renders at that degree, whose Fisher has no columns for coefficients it does not use."""
        if not 0 <= degree <= self.sh_degree:
            raise ValueError(f"sh degree {degree} outside 0..{self.sh_degree} (the stored degree)")
        return self.replace(shN=self.shN[:, :num_sh_bases(degree) - 1])

    def index(self, idx: Tensor) -> "Gaussians":
        return Gaussians(**{k: v[idx] for k, v in self.params().items()})

    def permute(self, perm: Tensor) -> "Gaussians":
        return self.index(perm)

    @staticmethod
    def cat(items: "list[Gaussians]") -> "Gaussians":
        return Gaussians(**{f.name: torch.cat([getattr(g, f.name) for g in items])
                            for f in fields(Gaussians)})

    # -- constructors ---------------------------------------------------------------------
    @staticmethod
    def from_points(points: Tensor, colors: Tensor, sh_degree: int = 3, scale: Tensor | float = 0.01,
                    opacity: float = 0.1) -> "Gaussians":
        """Isotropic Gaussians at ``points`` [N, 3] with RGB ``colors`` [N, 3] in [0, 1].

        ``scale`` is a float or [N] per-point scale (3DGS uses the mean distance to 3 neighbours).
        """
        n = points.shape[0]
        if n == 0:
            raise ValueError("points: cannot build Gaussians from an empty point cloud")
        scale_t = torch.as_tensor(scale, dtype=points.dtype, device=points.device).expand(n)
        quats = points.new_zeros(n, 4)
        quats[:, 0] = 1
        sh0 = ((colors - 0.5) / SH_C0)[:, None, :]
        shn = points.new_zeros(n, num_sh_bases(sh_degree) - 1, 3)
        logit = torch.logit(points.new_full((n,), opacity))
        return Gaussians(points.clone(), torch.log(scale_t)[:, None].repeat(1, 3), quats, logit,
                         sh0.clone(), shn)


@torch.no_grad()
def all_finite(tensors: list[Tensor]) -> bool:
    """True when no tensor holds NaN or inf. One reduction per tensor: a sum is finite whenever
    its terms are, unless it overflows, which the exact element check then settles."""
    sums = torch.stack([t.detach().sum() for t in tensors])
    if bool(torch.isfinite(sums.sum())):
        return True
    return all(bool(torch.isfinite(t).all()) for t in tensors)


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """Rotation matrices [..., 3, 3] from quaternions [..., 4] in (w, x, y, z) order (normalised here)."""
    q = torch.nn.functional.normalize(quats, dim=-1)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(*quats.shape[:-1], 3, 3)


def scaled_rotations(log_scales: Tensor, quats: Tensor) -> Tensor:
    """R S [N, 3, 3], the square root of the world covariance (R S)(R S)^T."""
    return quat_to_rotmat(quats) * torch.exp(log_scales)[:, None, :]
