"""``gaussmi``: GauSS-MI adapted to RGB only.

Each Gaussian keeps a reliability log-odds per viewing-direction bin (6 cube-face bins of the
direction Gaussian -> camera). Every taken view updates it from the rendering error of the
current model: a pixel with error e is reliable with probability r = exp(-e^2 / (2 sigma^2))
(clamped to [0.05, 0.95]) and the Gaussian's log-odds in that view's bin gain
sum_p w_pg logit(r_p). A candidate's score is the binary entropy of each Gaussian's reliability in
the candidate's direction bin, alpha-T composited and summed over pixels (argmax). The log-odds
are rebuilt from all taken views with the current model every round (the model changed).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from pipeline.bounds import FLOAT, bounded, require_bounds
from pipeline.acquisition.base import Selection, SelectionContext, timed_selection
from pipeline.acquisition.rendered_stats import render_feature, weighted_pixel_sums
from pipeline.splat import render


def direction_bins(means: torch.Tensor, center: torch.Tensor) -> torch.Tensor:
    """Cube-face bin (0..5) of the unit direction Gaussian -> camera centre, [N]."""
    d = center - means
    axis = d.abs().argmax(dim=1)
    positive = d.gather(1, axis[:, None])[:, 0] > 0
    return axis * 2 + positive.long()


@dataclass
class GaussMIStrategy:
    name: str = "gaussmi"
    error_sigma: float = bounded(0.1, FLOAT, gt=0)

    def __post_init__(self) -> None:
        require_bounds(self)

    def log_odds(self, ctx: SelectionContext):
        g = ctx.gaussians.detach()
        logits = g.means.new_zeros(len(g), 6, dtype=torch.float64)
        if ctx.taken_images is None:
            raise ValueError("gaussmi needs the taken views' images (ctx.taken_images)")
        for i in range(len(ctx.taken)):
            cam = ctx.taken[i]
            with torch.no_grad():
                pred = render(g, cam, ctx.background, settings=ctx.settings).rgb[0]
            err = (pred - ctx.taken_images[i].to(pred)).square().mean(-1)  # [H, W]
            r = torch.exp(-err / (2 * self.error_sigma ** 2)).clamp(0.05, 0.95)
            sums = weighted_pixel_sums(g, cam, torch.logit(r)[None], ctx.settings)
            bins = direction_bins(g.means, cam.centers[0])
            logits[torch.arange(len(g)), bins] += sums[:, 0].double()
        return logits

    def select(self, ctx: SelectionContext, count: int = 1) -> Selection:
        def run(order):
            logits = self.log_odds(ctx)
            pool = ctx.candidates[order]
            scores = torch.empty(len(order), dtype=torch.float64)
            g = ctx.gaussians.detach()
            for i in range(len(order)):
                p = torch.sigmoid(logits[torch.arange(len(g)), direction_bins(g.means, pool.centers[i])])
                p = p.clamp(1e-12, 1 - 1e-12)
                entropy = -(p * torch.log2(p) + (1 - p) * torch.log2(1 - p))
                scores[i] = render_feature(g, pool[i], entropy, ctx.settings).sum()
            picks = torch.argsort(-scores, stable=True)[:count].tolist()
            return picks, scores
        return timed_selection(ctx, run)
