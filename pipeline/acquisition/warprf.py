"""``warprf``: WarpRF (Safadoust et al., WACV 2026), a training-free score written from its paper and
its public code (``sadrasafa/WarpRF``, ``active/warprf.py`` and ``utils/graphics_utils.py``), not
copied.

An accurate model renders views that agree with each other once one is warped into another with
the rendered geometry. For a candidate camera c the model renders its image I_c and its depth D_c
(the expected camera z). Every taken view t is rendered by the model too (its render, not its
photograph) and warped backwards into c: each pixel p of c is lifted to the 3D point
``D_c(p) K_c^-1 [u, v, 1]``, moved into t's camera and projected, and I_t is sampled there
bilinearly (outside t's image the sample is clamped to its border, as the released code's
``grid_sample(padding_mode='border')``). The disagreement of a pixel is the L1 distance over the
colour channels, and the most consistent taken view speaks for it:

    U(c) = sum_p min_t || warp_t->c(I_t)(p) - I_c(p) ||_1

The pick is the highest U (the view the model is least consistent about). A batch takes the
``count`` highest scores (the released selector sorts once; no update between picks). The score
needs no gradient and no Fisher; a candidate equal to a taken view scores 0.

Pixels the model leaves empty (no opacity) have depth 0 here and lift to the candidate's own
centre, as in the released code (which renders the same depth); both then compare the background.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from pipeline.acquisition.base import PoseScorer, Selection, SelectionContext, timed_selection
from pipeline.cameras import Cameras, pixel_centers

MIN_SOURCE_DEPTH = 1e-9  # |z| below this in the source camera is held at this size (no inf)


def pixel_centres(width: int, height: int) -> Tensor:
    """Homogeneous pixel centres [3, H*W] float64, row-major: (j + 0.5, i + 0.5, 1)."""
    u, v = pixel_centers(width, height, torch.float64)
    return torch.stack([u, v, torch.ones_like(u)])


def source_pixels(sources: Cameras, target: Cameras, target_depth: Tensor) -> Tensor:
    """Where each pixel of ``target`` (one camera) lands in each source camera, given the target's
    depth [H, W] (camera z): [S, H, W, 2] image coordinates (u, v) in the source, float64."""
    if len(target) != 1:
        raise ValueError(f"source_pixels takes one target camera, got {len(target)}")
    h, w = target.height, target.width
    k_t = target.Ks[0].double()
    view_t = target.viewmats[0].double()
    rays = torch.linalg.solve(k_t, pixel_centres(w, h))                    # [3, HW], z = 1
    points_cam = rays * target_depth.double().reshape(1, -1)                # [3, HW]
    points_world = view_t[:3, :3].T @ (points_cam - view_t[:3, 3:4])        # [3, HW]
    view_s = sources.viewmats.double()
    in_source = view_s[:, :3, :3] @ points_world + view_s[:, :3, 3:4]       # [S, 3, HW]
    projected = sources.Ks.double() @ in_source                             # [S, 3, HW]
    z = projected[:, 2:3]
    z = torch.where(z.abs() < MIN_SOURCE_DEPTH, torch.full_like(z, MIN_SOURCE_DEPTH), z)
    uv = projected[:, :2] / z                                               # [S, 2, HW]
    return uv.permute(0, 2, 1).reshape(len(sources), h, w, 2)


def warp_into(source_images: Tensor, sources: Cameras, target: Cameras, target_depth: Tensor) -> Tensor:
    """Backward-warp source images [S, H, W, 3] into the target camera with its depth [H, W]:
    [S, H, W, 3], bilinear, clamped to the source's border outside it."""
    uv = source_pixels(sources, target, target_depth)
    grid = torch.stack([2 * uv[..., 0] / sources.width - 1, 2 * uv[..., 1] / sources.height - 1], -1)
    images = source_images.permute(0, 3, 1, 2).double()                    # [S, 3, H, W]
    warped = torch.nn.functional.grid_sample(images, grid, mode="bilinear", padding_mode="border",
                                             align_corners=False)
    return warped.permute(0, 2, 3, 1)


def warp_disagreement(taken_images: Tensor, taken: Cameras, candidate_image: Tensor,
                      candidate: Cameras, candidate_depth: Tensor) -> float:
    """U(c): the pixel sum of the smallest L1 disagreement between the candidate's render
    [H, W, 3] and any taken view's render [T, H, W, 3] warped into it."""
    warped = warp_into(taken_images, taken, candidate, candidate_depth)    # [T, H, W, 3]
    l1 = (warped - candidate_image.double()).abs().sum(-1)                 # [T, H, W]
    return float(l1.min(0).values.sum())


@dataclass
class WarpRFStrategy:
    name: str = "warprf"

    def taken_renders(self, ctx: SelectionContext) -> Tensor:
        """The model's renders of the taken views, [T, H, W, 3]."""
        if len(ctx.taken) == 0:
            raise ValueError("warprf scores a candidate against the taken views: none is taken yet")
        return ctx.backend.render(ctx.taken).rgb

    def scores(self, ctx: SelectionContext, cameras: Cameras, taken_images: Tensor) -> Tensor:
        """U of each camera, [B] float64 (the higher, the less consistent the model)."""
        doors, out = ctx.backend, torch.empty(len(cameras), dtype=torch.float64)
        for i in range(len(cameras)):
            render = doors.render(cameras[i])
            out[i] = warp_disagreement(taken_images, ctx.taken, render.rgb[0], cameras[i], render.depth[0])
        return out

    def select(self, ctx: SelectionContext, count: int = 1) -> Selection:
        def run(order):
            scores = self.scores(ctx, ctx.candidates[order], self.taken_renders(ctx))
            return torch.argsort(-scores, stable=True)[:count].tolist(), scores
        return timed_selection(ctx, run)

    def pose_scorer(self, ctx: SelectionContext) -> PoseScorer:
        """U of any cameras, negated (a search minimises it); the taken renders made once."""
        taken_images = self.taken_renders(ctx)
        return PoseScorer(lambda cameras: -self.scores(ctx, cameras, taken_images), maximizes=True)
