"""The uncertainty experiment (paper Sec. "Uncertainty Quantification", sparsification figure).

Train on a seeded random subset of the training views (10 views, 2000 iterations at paper scale:
the first 2,000 iterations of the 3DGS recipe, ``sparsification_fit``), then let each method rank
the test views by its predicted uncertainty, from the same fixed model:

- ``gopre``: the view's predictive entropy 1/2 log det(2 pi e (J S J^T + tau^2 I)) under the
  Laplace posterior S = 1 / (H_train + lambda) (parameter-space form, paper Eq. predictive-entropy).
- ``fisherrf``: FisherRF's expected information gain sum_i F_x,i / (H_train,i + lambda).
- ``activenerf``: the rendered variance summed over pixels, variance attribute fitted by NLL.
- ``random``: a seeded random ranking; ``oracle``: the true PSNR (worst first).
Sparsification curves over deciles and AUSE against the oracle, with PSNR as the quality.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from pipeline.acquisition import SelectionContext
from pipeline.acquisition.activenerf import ActiveNeRFStrategy
from pipeline.active.config import EpisodeConfig
from pipeline.active.episode import initial_gaussians
from pipeline.active.plan import uniform_subset
from pipeline.interchange.results import UncertaintyResult
from pipeline.bounds import FLOAT, INT, bounded, require_bounds
from pipeline.cameras import Cameras
from pipeline.data.sampling import seeded_subset
from pipeline.data.scene import Scene
from pipeline.eval.metrics import evaluate_views
from pipeline.eval.sparsification import DECILES, ause, oracle_curve, random_curve, sparsification_curve
from pipeline.fisher.exact import FisherSpec, predictive_variance_maps, view_fisher
from pipeline.fisher.posterior import predictive_entropy
from pipeline.fisher.variance import POSTERIOR_LAMBDA, taken_views_posterior
from pipeline.fit.config import FitConfig
from pipeline.fit.trainer import Trainer
from pipeline.splat import Gaussians, render

METHODS = ("gopre", "fisherrf", "activenerf")


@dataclass(frozen=True)
class UncertaintyConfig:
    train_views: int = bounded(10, INT, ge=1)
    iterations: int = bounded(2000, INT, ge=1, usual_max=300_000)
    test_views: int | None = bounded(None, INT, ge=1, nullable=True)  # a uniform subset of the test split
    # (None: all)
    methods: tuple[str, ...] = METHODS
    lam: float = bounded(POSTERIOR_LAMBDA, FLOAT, gt=0)
    tau: float = bounded(1.0, FLOAT, gt=0)
    map_views: int = bounded(4, INT, ge=0)  # per-pixel uncertainty maps for this many test views
    seed: int = bounded(0, INT, ge=0)

    def __post_init__(self) -> None:
        require_bounds(self)
        unknown = sorted(set(self.methods) - set(METHODS))
        if not self.methods or unknown:
            raise ValueError(f"methods: {list(self.methods)!r} is not a non-empty list of {', '.join(METHODS)}")


def sparsification_fit(fit: FitConfig, iterations: int, seed: int) -> FitConfig:
    """The paper's "3DGS model ... for 2,000 iterations": the episode recipe's first ``iterations``
    steps, not the whole recipe compressed into them (at the paper preset: densification every 100
    iterations from 500, no opacity reset, an SH step every 1,000, the lr decaying over 30k)."""
    return fit.first_iterations(iterations).with_changes(seed=seed)


def fisher_uncertainties(gaussians: Gaussians, train: Cameras, test: Cameras, background: torch.Tensor,
                         cfg: UncertaintyConfig) -> tuple[dict[str, np.ndarray], torch.Tensor]:
    """gopre entropy and fisherrf EIG of each test view [V]; and the posterior variance S [N, P]."""
    spec = FisherSpec()
    h_train, s = taken_views_posterior(gaussians, train, background, spec, cfg.lam)  # [N, P] each
    entropy, eig = [], []
    outputs = test.width * test.height * 3
    for i in range(len(test)):
        f = view_fisher(gaussians, test[i], background, spec)[0]
        entropy.append(float(predictive_entropy(s.flatten(), f.flatten(), outputs, cfg.tau)))
        eig.append(float((f / (h_train + cfg.lam)).sum()))
    return {"gopre": np.array(entropy), "fisherrf": np.array(eig)}, s


def activenerf_uncertainties(gaussians: Gaussians, train: Cameras, train_images: torch.Tensor,
                             test: Cameras, background: torch.Tensor, seed: int) -> np.ndarray:
    ctx = SelectionContext(gaussians, test, list(range(len(test))), train, background,
                           torch.Generator().manual_seed(seed), taken_images=train_images)
    return ActiveNeRFStrategy().rendered_variance(ctx, test).sum((1, 2)).numpy()


def run_uncertainty_experiment(scene: Scene, episode: EpisodeConfig, cfg: UncertaintyConfig) -> UncertaintyResult:
    """Fit on a random subset, rank test views; returns per-view PSNR, each method's uncertainty,
    sparsification curves and AUSE, and per-pixel variance maps ([V, H, W, 3] tensors)."""
    pool = scene.split("train" if "train" in scene.splits else "all")
    test = scene.split("test" if "test" in scene.splits else "all")
    gen = torch.Generator().manual_seed(cfg.seed)
    train_ids = seeded_subset(list(range(len(pool))), min(cfg.train_views, len(pool)), gen)
    test_ids = uniform_subset([i for i in range(len(test))
                               if test is not pool or i not in set(train_ids)], cfg.test_views)
    fit = sparsification_fit(episode.fit, cfg.iterations, cfg.seed)
    train_cams, train_images = pool.cameras[train_ids], pool.images.stack(train_ids)
    trainer = Trainer(initial_gaussians(scene, episode.with_changes(fit=fit)), train_cams, train_images,
                      fit, scene.background)
    trainer.train(fit.iterations)
    g = trainer.rendered_gaussians
    test_cams, test_images = test.cameras[test_ids], test.images.stack(test_ids)
    psnr = np.array(evaluate_views(g, test_cams, test_images, scene.background, ssim=False).psnr)
    scores, s = fisher_uncertainties(g, train_cams, test_cams, scene.background, cfg)
    if "activenerf" in cfg.methods:
        scores["activenerf"] = activenerf_uncertainties(g, train_cams, train_images, test_cams,
                                                        scene.background, cfg.seed)
    scores = {k: v for k, v in scores.items() if k in cfg.methods}
    oracle = oracle_curve(psnr)
    curves = {name: sparsification_curve(psnr, u) for name, u in scores.items()}
    curves["random"], curves["oracle"] = random_curve(psnr, cfg.seed), oracle
    shown = test_ids[:cfg.map_views]
    with torch.no_grad():
        renders = render(g, test.cameras[shown], scene.background).rgb.clamp(0, 1)
    maps = predictive_variance_maps(g, test.cameras[shown], s, scene.background)
    return UncertaintyResult(train_ids, test_ids, psnr.tolist(), {k: v.tolist() for k, v in scores.items()},
                             list(DECILES), {k: v.tolist() for k, v in curves.items()},
                             {k: ause(v, oracle) for k, v in curves.items()}, shown, maps.float(), renders,
                             test.images.stack(shown))
