"""How close recovered poses are to known ones: a similarity transform (scale, rotation,
translation; Umeyama 1991) fitted from camera centres, then per camera the centre error after
alignment and the angle between the aligned and the true rotation.

Used to check structure-from-motion against a scene whose poses are known (``gopre-data capture``
on the generated scene's renders, bonsai's photos against its staged model).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from torch import Tensor

from pipeline.cameras import Cameras


def umeyama(source: Tensor, target: Tensor) -> tuple[float, Tensor, Tensor]:
    """(s, R [3, 3], t [3]) minimising sum |s R source_i + t - target_i|^2; source, target [P, 3]
    float64, P >= 3 not collinear."""
    if source.shape != target.shape or source.shape[0] < 3:
        raise ValueError(f"umeyama: need matching [P >= 3, 3] point sets, got {tuple(source.shape)} "
                         f"and {tuple(target.shape)}")
    mu_s, mu_t = source.mean(0), target.mean(0)
    xs, xt = source - mu_s, target - mu_t
    cov = xt.T @ xs / len(source)
    u, d, vt = torch.linalg.svd(cov)
    sign = torch.ones(3, dtype=source.dtype)
    if torch.det(u) * torch.det(vt) < 0:
        sign[2] = -1
    rot = u @ torch.diag(sign) @ vt
    var_s = xs.square().sum() / len(source)
    scale = float((d * sign).sum() / var_s)
    return scale, rot, mu_t - scale * rot @ mu_s


@dataclass
class PoseErrors:
    cameras: int
    scene_extent: float                 # the true centres' largest distance from their mean
    median_centre_error: float          # as a fraction of scene_extent
    max_centre_error: float             # as a fraction of scene_extent
    median_rotation_error_deg: float
    max_rotation_error_deg: float
    scale: float

    def to_dict(self) -> dict:
        return asdict(self)


def pose_errors(true: Cameras, estimated: Cameras, fit_on: list[int] | None = None) -> PoseErrors:
    """The estimated cameras [C] against the true ones [C] (same order), after the similarity that
    best maps the estimated centres onto the true (fitted on the cameras ``fit_on`` only, when
    given: outliers left out of the fit are still measured)."""
    return pose_error_arrays(true, estimated, fit_on)[0]


def pose_error_arrays(true: Cameras, estimated: Cameras, fit_on: list[int] | None = None
                      ) -> tuple[PoseErrors, Tensor, Tensor]:
    """``pose_errors`` and the per-camera centre errors [C] (over the extent) and rotation errors [C]
    (degrees) it summarises."""
    if len(true) != len(estimated):
        raise ValueError(f"pose_errors: {len(true)} true and {len(estimated)} estimated cameras")
    c_true, c_est = true.centers.double(), estimated.centers.double()
    fit = list(range(len(true))) if fit_on is None else list(fit_on)
    scale, rot, shift = umeyama(c_est[fit], c_true[fit])
    aligned = c_est @ (scale * rot).T + shift
    extent = float((c_true - c_true.mean(0)).norm(dim=1).max())
    centre = (aligned - c_true).norm(dim=1) / extent
    # world->camera rotations: the estimated world is rot-rotated into the true one, so the
    # aligned world->camera rotation is R_est rot^T
    r_true, r_est = true.viewmats[:, :3, :3].double(), estimated.viewmats[:, :3, :3].double() @ rot.T
    cos = ((r_true.transpose(1, 2) @ r_est).diagonal(dim1=1, dim2=2).sum(1) - 1) / 2
    angle = torch.rad2deg(torch.arccos(cos.clamp(-1, 1)))
    return (PoseErrors(len(true), extent, float(centre.median()), float(centre.max()), float(angle.median()),
                       float(angle.max()), scale), centre, angle)


def matched(true_names: list[str], true: Cameras, est_names: list[str], estimated: Cameras,
            key=lambda name: name.rsplit("/", 1)[-1].rsplit(".", 1)[0]) -> tuple[Cameras, Cameras, list[str]]:
    """The cameras of both sets whose names match (by file stem), in the true set's order."""
    index = {key(n): i for i, n in enumerate(est_names)}
    pairs = [(i, index[key(n)]) for i, n in enumerate(true_names) if key(n) in index]
    if len(pairs) < 3:
        raise ValueError(f"only {len(pairs)} cameras are in both sets (matched by file name)")
    ti, ei = zip(*pairs)
    return true[list(ti)], estimated[list(ei)], [true_names[i] for i in ti]


def relative_rotation_errors(true: Cameras, estimated: Cameras) -> Tensor:
    """Per camera [C], degrees: the median over the other cameras j of the angle between the true
    relative rotation R_i R_j^T and the estimated one. No alignment enters it: a global rotation of
    either set leaves it at zero, while a camera turned against the others shows in its own figure
    and, once in the median of each of the others, not at all."""
    if len(true) != len(estimated) or len(true) < 2:
        raise ValueError(f"relative_rotation_errors: need matching sets of >= 2 cameras, got {len(true)} "
                         f"and {len(estimated)}")
    r_true, r_est = true.viewmats[:, :3, :3].double(), estimated.viewmats[:, :3, :3].double()
    rel_true = r_true[:, None] @ r_true.transpose(1, 2)[None]    # [C, C, 3, 3]: R_i R_j^T
    rel_est = r_est[:, None] @ r_est.transpose(1, 2)[None]
    cos = ((rel_true.transpose(-1, -2) @ rel_est).diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2
    angle = torch.rad2deg(torch.arccos(cos.clamp(-1, 1)))        # [C, C], zero on the diagonal
    others = angle[~torch.eye(len(true), dtype=torch.bool)].reshape(len(true), len(true) - 1)  # [C, C-1]
    return others.median(dim=1).values
