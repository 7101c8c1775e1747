"""Depth error of a trained model where a truth is known: absolute relative error and RMSE of the
rendered depth (the composited camera z) where the model renders opaquely (alpha >= ``MIN_ALPHA``),
over the views given, and a depth AUSE when a per-pixel uncertainty is given.

- ``depth_errors``: against a dense truth (the generated scene's ray-cast depth), on the pixels the
  true surface covers;
- ``sparse_depth_errors``: against the structure-from-motion points each view observed (a COLMAP
  scene: the points of the view's own track, so a point hidden in that view is never compared), at
  the pixel each projects to: the point's camera z is the truth there.

The AUSE (``ause_abs_rel``) ranks the scored pixels by the uncertainty given (the colour variance
summed over channels: no depth variance is computed) and sparsifies their absolute relative depth
error, both curves divided by their largest value (FisherRF's depth AUSE; WarpRF's depth-MAE AUSE
is the same area over the absolute error)."""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from torch import Tensor

from pipeline.eval.pixel_uncertainty import ause_max

MIN_ALPHA = 0.5


@dataclass(frozen=True)
class DepthErrors:
    pixels: int          # scored pixels (points), over all views
    abs_rel: float       # mean |d - d*| / d*
    rmse: float          # sqrt(mean (d - d*)^2), in scene units
    ause_abs_rel: float | None = None  # AUSE of |d - d*| / d* ranked by the uncertainty (max-norm.)

    def to_dict(self) -> dict:
        return asdict(self)


def depth_errors(depth: Tensor, alpha: Tensor, truth: Tensor, uncertainty: Tensor | None = None) -> DepthErrors | None:
    """depth, alpha, truth [C, H, W] (truth inf where no surface), uncertainty [C, H, W] or None;
    None when no pixel is scored."""
    if not (depth.shape == alpha.shape == truth.shape):
        raise ValueError(f"depth, alpha and truth must be [C, H, W] alike, got {tuple(depth.shape)}, "
                         f"{tuple(alpha.shape)}, {tuple(truth.shape)}")
    if uncertainty is not None and uncertainty.shape != depth.shape:
        raise ValueError(f"uncertainty must be [C, H, W] = {tuple(depth.shape)}, got {tuple(uncertainty.shape)}")
    d, t = depth.detach().double().cpu(), truth.detach().double().cpu()
    keep = torch.isfinite(t) & (t > 0) & (alpha.detach().cpu() >= MIN_ALPHA)
    if not bool(keep.any()):
        return None
    u = None if uncertainty is None else uncertainty.detach().double().cpu()[keep]
    return _errors(d[keep], t[keep], u)


def sparse_depth_errors(depth: Tensor, alpha: Tensor, viewmats: Tensor, Ks: Tensor, points: list[Tensor],
                        uncertainty: Tensor | None = None) -> DepthErrors | None:
    """depth, alpha [C, H, W] rendered by cameras (viewmats [C, 4, 4] world->camera, OpenCV; Ks
    [C, 3, 3] at that resolution), points: per view the [M_c, 3] world points it observed;
    uncertainty [C, H, W] or None. Each point in front of its camera and inside the image is
    compared at the pixel it falls in; None when none is scored."""
    if not (depth.shape == alpha.shape) or len(points) != depth.shape[0]:
        raise ValueError(f"depth and alpha must be [C, H, W] alike with one point set per view, got "
                         f"{tuple(depth.shape)}, {tuple(alpha.shape)} and {len(points)} point sets")
    rendered, truth, scores = [], [], []
    height, width = depth.shape[1:]
    for c, world in enumerate(points):
        if world is None or len(world) == 0:
            continue
        vm, k = viewmats[c].double().cpu(), Ks[c].double().cpu()
        cam = world.double().cpu() @ vm[:3, :3].T + vm[:3, 3]  # [M, 3] camera frame
        z = cam[:, 2]
        front = z > 1e-9
        uv = cam[front] @ k.T
        px = torch.floor(uv[:, 0] / uv[:, 2]).long()  # pixel (x, y) whose square holds the point
        py = torch.floor(uv[:, 1] / uv[:, 2]).long()
        inside = (px >= 0) & (px < width) & (py >= 0) & (py < height)
        px, py, zc = px[inside], py[inside], z[front][inside]
        opaque = alpha[c].detach().cpu()[py, px] >= MIN_ALPHA
        rendered.append(depth[c].detach().double().cpu()[py, px][opaque])
        truth.append(zc[opaque])
        if uncertainty is not None:
            scores.append(uncertainty[c].detach().double().cpu()[py, px][opaque])
    if not rendered or sum(len(r) for r in rendered) == 0:
        return None
    return _errors(torch.cat(rendered), torch.cat(truth), torch.cat(scores) if uncertainty is not None else None)


def _errors(d: Tensor, t: Tensor, u: Tensor | None) -> DepthErrors:
    """d, t, u [P]: rendered and true depth, and the uncertainty (or None), of the scored pixels."""
    rel = (d - t).abs() / t
    ause = None if u is None else ause_max(rel.numpy(), u.numpy())[0]
    return DepthErrors(int(len(d)), float(rel.mean()), float((d - t).square().mean().sqrt()), ause)
