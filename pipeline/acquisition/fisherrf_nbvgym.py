"""``fisherrf_nbvgym``: the FisherRF variant NBV-Gym (CVPR 2026, ``chengine/nbv_gym``) measured COVER
against, written from its public code (``nbv_gym/model.py``: ``FisherSplatModel``, and
``view_selector.py``), not copied. It is not FisherRF's released score (``fisherrf``):

- every taken view's diagonal Hessian is summed over the views **and over every parameter** of a
  Gaussian into one number H_g (FisherRF keeps one entry per parameter);
- a candidate renders the map ``sum_g w_pg H_g z_g`` (alpha-T compositing, black background), where
  z_g is the Gaussian's camera depth in the candidate (clamped at 0), and scores its mean over the
  pixels where the map is positive;
- the pick is the **highest** mean (NBV-Gym negates it and sorts ascending), so the view that sees
  the most-observed Gaussians, far away, wins: there is no division by H_train + lambda (FisherRF's
  information gain) and the Hessian is not inverted; a batch takes the ``count`` highest (top-k, no
  update between picks).

What differs from NBV-Gym's code, by necessity: its Hessian is FisherRF's modified CUDA rasterizer
run on the already-activated tensors (exp scales, sigmoid opacities), for the RGB image plus the
depth image (weights 1 and 1); here H_g is the released FisherRF Hessian of the RGB image that this
package computes (``FisherSpec(hessian="fisherrf_released")``: channel-summed derivatives, the
activation's derivative carried once, rotations included as NBV-Gym includes them), with no depth
term (no Fisher of the depth image exists here). The ordering it induces (highest seen-and-deep
Hessian mass) is the variant's; its absolute values are not NBV-Gym's.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor

from pipeline.acquisition.base import Selection, SelectionContext, in_chunks, timed_selection
from pipeline.acquisition.rendered_stats import render_feature
from pipeline.cameras import Cameras
from pipeline.fisher.exact import FisherSpec
from pipeline.fisher.features import PARAM_GROUPS
from pipeline.splat import Gaussians, RenderSettings


def gaussian_depths(gaussians: Gaussians, camera: Cameras) -> Tensor:
    """Each Gaussian's camera z in one camera, clamped at 0: [N]."""
    view = camera.viewmats[0].to(gaussians.means)
    return (gaussians.means.detach() @ view[2, :3] + view[2, 3]).clamp_min(0)


def depth_weighted_map(gaussians: Gaussians, camera: Cameras, hessian: Tensor,
                       settings: RenderSettings) -> Tensor:
    """The map sum_g w_pg H_g z_g of one camera, [H, W] (H_g: ``hessian`` [N])."""
    values = hessian.to(gaussians.means.dtype) * gaussian_depths(gaussians, camera)
    return render_feature(gaussians, camera, values, settings)[0]


def positive_mean(values: Tensor) -> float:
    """Mean over the entries that are > 0 (0 when none is)."""
    positive = values > 0
    return float((values * positive).sum() / positive.sum().clamp_min(1))


@dataclass
class FisherRFNbvGymStrategy:
    name: str = "fisherrf_nbvgym"
    spec: FisherSpec = field(init=False)

    def __post_init__(self) -> None:
        self.spec = FisherSpec(groups=PARAM_GROUPS, hessian="fisherrf_released")

    def gaussian_hessian(self, ctx: SelectionContext) -> Tensor:
        """H_g: the taken views' Hessians summed over views and parameters, [N] float64."""
        chunks = in_chunks(ctx, ctx.taken, lambda cams: ctx.backend.training_hessian(cams, self.spec).sum(-1))
        return sum(chunks, torch.zeros(len(ctx.gaussians), dtype=torch.float64))

    def scores(self, ctx: SelectionContext, cameras: Cameras, hessian: Tensor) -> Tensor:
        """Each camera's mean of its depth-weighted Hessian map, [B] float64 (the higher wins)."""
        g = ctx.gaussians.detach()
        return torch.tensor([positive_mean(depth_weighted_map(g, cameras[i], hessian, ctx.settings))
                             for i in range(len(cameras))], dtype=torch.float64)

    def select(self, ctx: SelectionContext, count: int = 1) -> Selection:
        def run(order):
            scores = self.scores(ctx, ctx.candidates[order], self.gaussian_hessian(ctx))
            return torch.argsort(-scores, stable=True)[:count].tolist(), scores
        return timed_selection(ctx, run)
