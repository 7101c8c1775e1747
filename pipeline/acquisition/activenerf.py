"""``activenerf``: ActiveNeRF adapted to 3DGS (as FisherRF adapted it).

Each Gaussian carries a variance attribute beta_g^2 = exp(log_var_g), trained with ActiveNeRF's
Gaussian NLL on the taken views, sum_p |I_p - C_p|^2 / (2 V_p) + log(V_p) / 2, where the rendered
variance V_p = sum_g w_pg beta_g^2 + v_min is alpha-T composited like colour. Here the attribute is
fitted each round with the current geometry and colours held fixed. A candidate's score is the
rendered prior-minus-posterior variance summed over pixels, sum_p (V_p - (1/V_p + 1/tau^2)^-1),
argmax.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from pipeline.acquisition.base import Selection, SelectionContext, timed_selection
from pipeline.acquisition.rendered_stats import render_feature
from pipeline.splat import render


@dataclass
class ActiveNeRFStrategy:
    name: str = "activenerf"
    steps: int = 60
    lr: float = 0.1
    min_variance: float = 1e-3
    tau: float = 1.0
    init_log_var: float = -3.0

    def fit_variance(self, ctx: SelectionContext) -> torch.Tensor:
        """log_var [N] fitted by NLL on the taken views (geometry and colour fixed)."""
        if ctx.taken_images is None:
            raise ValueError("activenerf needs the taken views' images (ctx.taken_images)")
        g = ctx.gaussians.detach()
        log_var = g.means.new_full((len(g),), self.init_log_var, requires_grad=True)
        with torch.no_grad():
            residual = [(render(g, ctx.taken[i], ctx.background, settings=ctx.settings).rgb[0]
                         - ctx.taken_images[i].to(g.means)).square().sum(-1) for i in range(len(ctx.taken))]
        opt = torch.optim.Adam([log_var], lr=self.lr)
        for step in range(self.steps):
            i = step % len(ctx.taken)
            with torch.enable_grad():
                out = render(g, ctx.taken[i], settings=ctx.settings,  # only the feature channel is read
                             extra_features=torch.exp(log_var)[:, None])
                v = out.rgb[0, ..., 3] + self.min_variance
                nll = (residual[i] / (2 * v) + 0.5 * torch.log(v)).mean()
                opt.zero_grad()
                nll.backward()
            opt.step()
        return log_var.detach()

    def rendered_variance(self, ctx: SelectionContext, cameras) -> torch.Tensor:
        """Prior rendered variance V_p of each view, [C, H, W] float64 (attribute fitted first)."""
        variance = torch.exp(self.fit_variance(ctx))
        v = render_feature(ctx.gaussians, cameras, variance, ctx.settings).double()
        return v + self.min_variance

    def select(self, ctx: SelectionContext, count: int = 1) -> Selection:
        def run(order):
            v = self.rendered_variance(ctx, ctx.candidates[order])
            scores = (v - 1.0 / (1.0 / v + 1.0 / self.tau ** 2)).sum((1, 2))
            return torch.argsort(-scores, stable=True)[:count].tolist(), scores
        return timed_selection(ctx, run)
