"""Pinhole cameras in the OpenCV convention.

Conventions (written once, used everywhere):
- Camera frame: x right, y down, z forward (OpenCV / COLMAP).
- ``viewmats`` are world->camera 4x4 matrices: ``x_cam = R x_world + t``.
- ``Ks`` are 3x3 intrinsics ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` in pixels.
- Pixel centres: pixel (row i, column j) has its centre at image coordinates
  ``(u, v) = (j + 0.5, i + 0.5)``; the image's top-left corner is (0, 0) (COLMAP's convention).
- Images are ``[H, W, 3]`` tensors with values in [0, 1].
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass(frozen=True)
class Cameras:
    """A batch of C pinhole cameras sharing one image size.

    viewmats: [C, 4, 4] world->camera; Ks: [C, 3, 3]; width, height in pixels.
    """

    viewmats: Tensor
    Ks: Tensor
    width: int
    height: int

    def __post_init__(self) -> None:
        vm, ks = self.viewmats, self.Ks
        if vm.ndim != 3 or vm.shape[-2:] != (4, 4):
            raise ValueError(f"viewmats must be [C, 4, 4], got {tuple(vm.shape)}")
        if ks.ndim != 3 or ks.shape[-2:] != (3, 3) or ks.shape[0] != vm.shape[0]:
            raise ValueError(f"Ks must be [C, 3, 3] with C={vm.shape[0]}, got {tuple(ks.shape)}")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise ValueError(f"width and height must be positive, got {self.width}x{self.height}")
        if not bool(torch.isfinite(vm).all()):
            raise ValueError("viewmats contain NaN or inf")
        if not bool(torch.isfinite(ks).all()):
            raise ValueError("Ks contain NaN or inf")
        if bool((ks[:, 0, 0] <= 0).any() | (ks[:, 1, 1] <= 0).any()):
            raise ValueError("Ks: focal lengths fx, fy must be positive")

    def __len__(self) -> int:
        return self.viewmats.shape[0]

    def __getitem__(self, index) -> "Cameras":
        """Select cameras by int, slice, list or index tensor; always returns a batch."""
        if isinstance(index, int):
            index = [index]
        return Cameras(self.viewmats[index], self.Ks[index], self.width, self.height)

    def to(self, device=None, dtype=None) -> "Cameras":
        """These cameras on ``device`` in ``dtype``; ``self`` when both already match (the record
        is frozen, so sharing it is safe, and a training step does not re-validate its camera)."""
        viewmats = self.viewmats.to(device=device, dtype=dtype)
        Ks = self.Ks.to(device=device, dtype=dtype)
        if viewmats is self.viewmats and Ks is self.Ks:
            return self
        return Cameras(viewmats, Ks, self.width, self.height)

    @property
    def centers(self) -> Tensor:
        """Camera centres in world coordinates, [C, 3]."""
        rot, trans = self.viewmats[:, :3, :3], self.viewmats[:, :3, 3]
        return -(rot.transpose(1, 2) @ trans[..., None])[..., 0]

    @staticmethod
    def cat(batches: "list[Cameras]") -> "Cameras":
        first = batches[0]
        if any((b.width, b.height) != (first.width, first.height) for b in batches):
            raise ValueError("Cameras.cat: all batches must share one image size")
        return Cameras(torch.cat([b.viewmats for b in batches]), torch.cat([b.Ks for b in batches]),
                       first.width, first.height)


def pixel_centers(width: int, height: int, dtype=torch.float32, device=None) -> tuple[Tensor, Tensor]:
    """(u, v) of every pixel centre, [H*W] each, row-major: (j + 0.5, i + 0.5) (the convention above)."""
    v, u = torch.meshgrid(torch.arange(height, device=device), torch.arange(width, device=device),
                          indexing="ij")
    return (u.reshape(-1) + 0.5).to(dtype), (v.reshape(-1) + 0.5).to(dtype)


def look_at(eyes: Tensor, targets: Tensor, up: Tensor) -> Tensor:
    """World->camera matrices for cameras at ``eyes`` [C, 3] looking at ``targets`` [C, 3].

    ``up`` [3] is the world direction that appears as up (-y) in the image. Returns [C, 4, 4].
    """
    forward = torch.nn.functional.normalize(targets - eyes, dim=-1)  # camera +z
    right = torch.nn.functional.normalize(torch.cross(forward, up.expand_as(forward), dim=-1), dim=-1)
    down = torch.cross(forward, right, dim=-1)  # camera +y
    rot = torch.stack([right, down, forward], dim=1)  # rows = camera axes in world, [C, 3, 3]
    viewmats = torch.zeros(eyes.shape[0], 4, 4, dtype=eyes.dtype, device=eyes.device)
    viewmats[:, :3, :3] = rot
    viewmats[:, :3, 3] = -(rot @ eyes[..., None])[..., 0]
    viewmats[:, 3, 3] = 1
    return viewmats


def intrinsics_from_fov(fov_x: float, width: int, height: int, count: int, dtype=torch.float32,
                        device=None) -> Tensor:
    """Ks [count, 3, 3] for a horizontal field of view (radians), square pixels, centred."""
    focal = 0.5 * width / torch.tan(torch.tensor(0.5 * fov_x, dtype=torch.float64)).item()
    k = torch.tensor([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1]], dtype=dtype,
                     device=device)
    return k.expand(count, 3, 3).clone()
