"""The taken views' posterior and the per-pixel predictive variance maps it gives: the one recipe
behind the per-round variance images, the viewer's variance panel and the uncertainty
experiment, with one prior lambda."""

from __future__ import annotations

from torch import Tensor

from pipeline.cameras import Cameras
from pipeline.fisher.exact import FisherSpec, predictive_variance_maps, view_fisher
from pipeline.fisher.posterior import POSTERIOR_LAMBDA, posterior_variance
from pipeline.splat import Gaussians


def taken_views_posterior(gaussians: Gaussians, taken: Cameras, background: Tensor,
                          spec: FisherSpec = FisherSpec(),
                          lam: float = POSTERIOR_LAMBDA) -> tuple[Tensor, Tensor]:
    """(H_train [N, P], the sum of the taken views' exact Fishers; S = 1 / (H_train + lam) [N, P])."""
    h_train = view_fisher(gaussians, taken, background, spec).sum(0)
    return h_train, posterior_variance(h_train, lam)


def variance_maps(gaussians: Gaussians, taken: Cameras, cameras: Cameras, background: Tensor,
                  lam: float = POSTERIOR_LAMBDA) -> Tensor:
    """Per-pixel predictive variance [C, H, W] of ``cameras`` (summed over the colour channels)
    under the posterior of the ``taken`` views."""
    return channel_variance_maps(gaussians, taken, cameras, background, lam).sum(-1)


def channel_variance_maps(gaussians: Gaussians, taken: Cameras, cameras: Cameras, background: Tensor,
                          lam: float = POSTERIOR_LAMBDA) -> Tensor:
    """Per-pixel predictive variance [C, H, W, 3] of ``cameras``, per colour channel."""
    _, s = taken_views_posterior(gaussians, taken, background, lam=lam)
    return predictive_variance_maps(gaussians, cameras, s, background)
