"""``activenerf``: ActiveNeRF adapted to 3DGS as FisherRF's port does it (the paper's baseline).

Each Gaussian g carries a variance attribute beta_g^2 = exp(log_var_g). As in the port's
rasteriser (FisherRF ``var_diff/cuda_rasterizer/forward.cu``), a pixel's prior variance composites
it with the *squared* compositing weights w = alpha T,
    V_p = v_0 + sum_g w_pg^2 beta_g^2                     (v_0 = 1e-4, the port's initial value)
and its posterior variance after observing that pixel is the per-Gaussian posterior sum
    P_p = sum_g w_pg^2 / (1 / beta_g^2 + w_pg^2 / V_p).
A candidate's score is the prior-minus-posterior variance summed over its pixels,
sum_p (V_p - P_p), argmax (ActiveNeRF's variance reduction).

The attribute is fitted each round by ActiveNeRF's Gaussian NLL on the taken views,
sum_p |I_p - C_p|^2 / (2 V_p) + log(V_p) / 2, for ``steps`` Adam steps with the geometry and colours
held fixed (the port trains it jointly with the splat; a deliberate deviation, reports/fidelity.md).
The port's kernel weights a Gaussian by alpha times the transmittance *after* it; here w is the
3DGS compositing weight alpha T before it (the weight colour uses), also stated in the report.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from pipeline.bounds import FLOAT, INT, bounded, require_bounds
from pipeline.acquisition.base import Selection, SelectionContext, timed_selection
from pipeline.acquisition.rendered_stats import view_compositing_weights
from pipeline.splat import render
from pipeline.splat.rasterize import CompositingWeights


@dataclass
class ActiveNeRFStrategy:
    name: str = "activenerf"
    steps: int = bounded(60, INT, ge=0, usual_max=100_000)
    lr: float = bounded(0.1, FLOAT, gt=0)
    min_variance: float = bounded(1e-4, FLOAT, gt=0)
    init_log_var: float = bounded(-3.0, FLOAT)

    def __post_init__(self) -> None:
        require_bounds(self)

    def fit_variance(self, ctx: SelectionContext) -> torch.Tensor:
        """log_var [N] fitted by NLL on the taken views (geometry and colour fixed)."""
        if ctx.taken_images is None:
            raise ValueError("activenerf needs the taken views' images (ctx.taken_images)")
        g = ctx.gaussians.detach()
        log_var = g.means.new_full((len(g),), self.init_log_var, requires_grad=True)
        if self.steps == 0:
            return log_var.detach()
        weights, residual = [], []
        with torch.no_grad():
            for i in range(len(ctx.taken)):
                weights.append(view_compositing_weights(g, ctx.taken[i], ctx.settings))
                rgb = render(g, ctx.taken[i], ctx.background, settings=ctx.settings).rgb[0]
                residual.append((rgb - ctx.taken_images[i].to(g.means)).square().sum(-1))
        opt = torch.optim.Adam([log_var], lr=self.lr)
        for step in range(self.steps):
            i = step % len(ctx.taken)
            with torch.enable_grad():
                v = self.prior_variance(weights[i], torch.exp(log_var))
                nll = (residual[i] / (2 * v) + 0.5 * torch.log(v)).mean()
                opt.zero_grad()
                nll.backward()
            opt.step()
        return log_var.detach()

    def prior_variance(self, weights: CompositingWeights, variance: torch.Tensor) -> torch.Tensor:
        """V_p = v_0 + sum_g w_pg^2 beta_g^2, [H, W]."""
        return weights.composite(variance, power=2) + self.min_variance

    def posterior_variance(self, weights: CompositingWeights, variance: torch.Tensor,
                           prior: torch.Tensor) -> torch.Tensor:
        """P_p = sum_g w_pg^2 / (1 / beta_g^2 + w_pg^2 / V_p), [H, W]."""
        w2 = weights.weight.to(variance.dtype) ** 2
        entries = w2 / (1.0 / variance[weights.gaussian] + w2 / prior.reshape(-1)[weights.pixel])
        return weights.per_pixel(entries)

    def variances(self, ctx: SelectionContext, cameras) -> tuple[torch.Tensor, torch.Tensor]:
        """Prior and posterior rendered variance of each view, both [C, H, W] float64 (the
        attribute fitted first)."""
        variance = torch.exp(self.fit_variance(ctx)).double()
        priors, posteriors = [], []
        for i in range(len(cameras)):
            w = view_compositing_weights(ctx.gaussians, cameras[i], ctx.settings)
            prior = self.prior_variance(w, variance)
            priors.append(prior)
            posteriors.append(self.posterior_variance(w, variance, prior))
        return torch.stack(priors), torch.stack(posteriors)

    def rendered_variance(self, ctx: SelectionContext, cameras) -> torch.Tensor:
        """Prior rendered variance V_p of each view, [C, H, W] float64 (attribute fitted first)."""
        return self.variances(ctx, cameras)[0]

    def select(self, ctx: SelectionContext, count: int = 1) -> Selection:
        def run(order):
            prior, posterior = self.variances(ctx, ctx.candidates[order])
            scores = (prior - posterior).sum((1, 2))
            return torch.argsort(-scores, stable=True)[:count].tolist(), scores
        return timed_selection(ctx, run)
