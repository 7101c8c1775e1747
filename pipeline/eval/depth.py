"""Depth error of a trained model where the truth is known (the generated scene): absolute relative
error and RMSE of the rendered depth (the composited camera z) on the pixels the true surface covers
and the model renders opaquely (alpha >= ``MIN_ALPHA``), over the views given."""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from torch import Tensor

MIN_ALPHA = 0.5


@dataclass(frozen=True)
class DepthErrors:
    pixels: int          # scored pixels, over all views
    abs_rel: float       # mean |d - d*| / d*
    rmse: float          # sqrt(mean (d - d*)^2), in scene units

    def to_dict(self) -> dict:
        return asdict(self)


def depth_errors(depth: Tensor, alpha: Tensor, truth: Tensor) -> DepthErrors | None:
    """depth, alpha, truth [C, H, W] (truth inf where no surface); None when no pixel is scored."""
    if not (depth.shape == alpha.shape == truth.shape):
        raise ValueError(f"depth, alpha and truth must be [C, H, W] alike, got {tuple(depth.shape)}, "
                         f"{tuple(alpha.shape)}, {tuple(truth.shape)}")
    d, t = depth.detach().double().cpu(), truth.detach().double().cpu()
    keep = torch.isfinite(t) & (t > 0) & (alpha.detach().cpu() >= MIN_ALPHA)
    if not bool(keep.any()):
        return None
    d, t = d[keep], t[keep]
    return DepthErrors(int(keep.sum()), float(((d - t).abs() / t).mean()), float((d - t).square().mean().sqrt()))
