"""Fitting a splat to a set of posed images with the 3DGS recipe.

``Trainer`` is stateful so the active loop can train, add views, reset opacities and continue
with the same optimizer and schedules; ``fit`` is the one-shot convenience wrapper.

A step whose loss or gradient is not finite never reaches the parameters: it is skipped and
counted, the state that produced it (parameters, camera, target) is saved for reproduction when the
trainer has a ``nonfinite_dir``, and more than ``NONFINITE_STEP_LIMIT`` such steps raise
``NonFiniteTraining`` naming the step, the view and the saved file.
"""

from __future__ import annotations

from typing import Callable

import math
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor
from tqdm.auto import tqdm

from pipeline.cameras import Cameras
from pipeline.fit.adam import FusedAdam
from pipeline.fit.config import FitConfig
from pipeline.fit.densify import DensifyStats, densify_and_prune, reset_opacity
from pipeline.fit.fused_step import StepGradients, fused_step_gradients
from pipeline.fit.losses import masked_pair, photometric_loss, psnr
from pipeline.splat import Gaussians, RenderSettings, render
from pipeline.splat.gaussians import all_finite
from pipeline.splat.training_view import fused_training_step, training_view_generic


NONFINITE_STEP_LIMIT = 10


class NonFiniteTraining(RuntimeError):
    """Too many training steps had a non-finite loss or gradient."""


def scene_extent(cameras: Cameras, what: str = "the training cameras") -> float:
    """3DGS scene scale: 1.1 x the largest distance of a camera centre from their mean.

    It scales the means' learning rate and the densification thresholds, so an extent of zero
    (one camera, or every centre at one point) is refused, naming ``what``, not divided by."""
    centers = cameras.centers.double().reshape(-1, 3)
    radius = float((centers - centers.mean(0)).norm(dim=1).max()) if len(centers) else 0.0
    rounding = 1e-9 * max(1.0, float(centers.abs().max()) if len(centers) else 1.0)  # far from 0
    if not radius > rounding:
        raise ValueError(f"{what}: the scene extent is zero ({len(cameras)} camera(s), every centre "
                         f"at one point); 3DGS scales the learning rate of the means and the "
                         f"densification thresholds by it, so it needs cameras at two places at least")
    return 1.1 * radius


@dataclass
class StepInfo:
    """One step: its loss, the model's size after it, and its render [H, W, 3] (detached) with the
    target, from which ``psnr`` is computed when read (the progress bar reads it every tenth step;
    computing it every step cost ~1% of training). A skipped step has neither: psnr is NaN."""

    step: int
    loss: float
    num_gaussians: int
    image: Tensor | None = None
    target: Tensor | None = None

    @property
    def psnr(self) -> float:
        if self.image is None or self.target is None:
            return float("nan")
        return float(psnr(self.image, self.target))


class Trainer:
    """Optimises ``gaussians`` on training views (cameras [C], images [C, H, W, 3])."""

    def __init__(self, gaussians: Gaussians, cameras: Cameras, images: Tensor, config: FitConfig,
                 background: Tensor | None = None, extent: float | None = None,
                 render_settings: RenderSettings = RenderSettings(), nonfinite_dir: Path | None = None,
                 masks: Tensor | None = None):
        self.config = config
        self.nonfinite_dir = nonfinite_dir
        self.nonfinite_steps = 0  # skipped steps (non-finite loss or gradient)
        self.settings = render_settings
        self.background = background if background is not None else images.new_zeros(3)
        self.extent = extent if extent is not None else scene_extent(cameras)
        self.generator = torch.Generator().manual_seed(config.seed)
        self.step = 0
        self._settle_from: int | None = None  # no density event after this step (``train``'s settle)
        self.params = {k: v.detach().clone().requires_grad_(True) for k, v in gaussians.params().items()}
        lr = config.lr
        rates = {"means": lr.means_init * self.extent, "log_scales": lr.log_scales, "quats": lr.quats,
                 "logit_opacities": lr.logit_opacities, "sh0": lr.sh0, "shN": lr.shN}
        # torch's fused Adam kernel, one call per parameter group, without torch.optim (pipeline/fit/adam.py)
        self.optimizer = FusedAdam([{"params": [p], "lr": rates[k], "name": k} for k, p in self.params.items()],
                                   eps=1e-15)
        self.stats = DensifyStats.zeros(len(gaussians), images)
        self._order: list[int] = []
        self.set_views(cameras, images, masks)

    # -- views --------------------------------------------------------------------------------
    def set_views(self, cameras: Cameras, images: Tensor, masks: Tensor | None = None) -> None:
        """The training views: cameras [C], images [C, H, W, 3]; ``masks`` [C, H, W] (1 = kept):
        the loss ignores masked-out pixels (``losses.masked_pair``)."""
        if images.ndim != 4 or images.shape[-1] != 3 or images.shape[0] != len(cameras):
            raise ValueError(f"images must be [C, H, W, 3] with C={len(cameras)}, got "
                             f"{tuple(images.shape)}")
        if images.shape[1:3] != (cameras.height, cameras.width):
            raise ValueError(f"images are {images.shape[2]}x{images.shape[1]} but cameras are "
                             f"{cameras.width}x{cameras.height}")
        if not bool(torch.isfinite(images).all()):
            raise ValueError("images contain NaN or inf")
        if masks is not None and masks.shape != images.shape[:3]:
            raise ValueError(f"masks must be [C, H, W] = {tuple(images.shape[:3])}, got {tuple(masks.shape)}")
        self.cameras, self.images, self.masks = cameras, images, masks
        self._view_cameras = [cameras[i] for i in range(len(cameras))]  # one per step otherwise
        self._order = []

    def _next_view(self) -> int:
        if not self._order:  # a fresh random permutation per epoch, as 3DGS
            self._order = torch.randperm(len(self.cameras), generator=self.generator).tolist()
        return self._order.pop()

    # -- state ----------------------------------------------------------------------------------
    @property
    def gaussians(self) -> Gaussians:
        return Gaussians(**{k: v.detach() for k, v in self.params.items()})

    @property
    def rendered_gaussians(self) -> Gaussians:
        """The model as it renders now: SH truncated to the active degree (what evaluation, the
        Fisher, the acquisition strategies and the saved result use)."""
        return self.gaussians.at_sh_degree(self.active_sh_degree)

    @property
    def active_sh_degree(self) -> int:
        return min(self.config.sh_degree, self.step // max(self.config.sh_degree_interval, 1))

    def _means_lr(self) -> float:
        horizon = self.config.lr_decay_iterations or self.config.iterations
        lr, t = self.config.lr, min(self.step / max(horizon, 1), 1.0)
        return self.extent * math.exp((1 - t) * math.log(lr.means_init) + t * math.log(lr.means_final))

    def state_dict(self) -> dict:
        """Everything needed to continue exactly where this trainer is (checkpointing)."""
        return {"params": {k: v.detach().clone() for k, v in self.params.items()},
                "optimizer": self.optimizer.state_dict(), "step": self.step, "extent": self.extent,
                "generator": self.generator.get_state(), "order": list(self._order),
                "stats": [self.stats.grad_sum, self.stats.count, self.stats.max_radii],
                "nonfinite_steps": self.nonfinite_steps,
                "active_sh_degree": self.active_sh_degree}  # read by exports, not by resume

    def load_state_dict(self, state: dict) -> None:
        """Restore a ``state_dict`` (the views are set separately, before this call)."""
        order = list(state["order"])
        self.params = {k: v.detach().clone().requires_grad_(True) for k, v in state["params"].items()}
        for group in self.optimizer.param_groups:
            group["params"] = [self.params[group["name"]]]
        self.optimizer.state.clear()
        self.optimizer.load_state_dict(state["optimizer"])
        self.step, self.extent = int(state["step"]), float(state["extent"])
        self.generator.set_state(state["generator"])
        self.stats = DensifyStats(*[t.clone() for t in state["stats"]])
        self.nonfinite_steps = int(state.get("nonfinite_steps", 0))
        self._order = order

    def reset_opacity(self, value: float | None = None) -> None:
        value = self.config.densify.opacity_reset_value if value is None else value
        self.params = reset_opacity(self.params, self.optimizer, value)

    # -- training -------------------------------------------------------------------------------
    def train_step(self) -> StepInfo:
        dcfg = self.config.densify
        self.step += 1
        for group in self.optimizer.param_groups:
            if group["name"] == "means":
                group["lr"] = self._means_lr()
        view = self._next_view()
        cams, target = self._view_cameras[view], self.images[view]
        mask = None if self.masks is None else self.masks[view]
        self._clear_grads()
        if fused_training_step(self.settings, self.background.device):
            step = self._fused_gradients(cams, target, mask)
        else:
            step = self._autograd_gradients(cams, target, mask)
        if not self._finite(step.loss):
            self._clear_grads()
            self._skip(view, step.loss)
            self._density_control()  # keeps periodic events on their schedule
            return StepInfo(self.step, float("nan"), self.params["means"].shape[0])
        if self.step < dcfg.stop:
            self.stats.update(step.means2d_grad, step.radii, cams.width, cams.height)
        self.optimizer.step()
        self._density_control()
        return StepInfo(self.step, step.loss, self.params["means"].shape[0], step.image, target)

    def _fused_gradients(self, cams: Cameras, target: Tensor, mask: Tensor | None = None) -> StepGradients:
        """The fused compiled step, no autograd: loss and gradients from the kernels, the
        gradients set on the parameters."""
        step = fused_step_gradients(self.params, cams, self.background, self.active_sh_degree,
                                    self.settings, target, self.config.ssim_weight, mask)
        for name, p in self.params.items():
            p.grad = step.grads[name]
        return step

    def _autograd_gradients(self, cams: Cameras, target: Tensor, mask: Tensor | None = None) -> StepGradients:
        """The step through autograd: ``render`` (any backend) and the torch loss (the oracles of
        the fused step); the gradients land on the parameters (``grads`` is empty)."""
        out = training_view_generic(self.gaussians_for_grad(), cams, self.background,
                                    self.active_sh_degree, self.settings)
        loss = photometric_loss(*masked_pair(out.image, target, mask), self.config.ssim_weight)
        loss.backward()
        return StepGradients(float(loss.detach()), {}, out.image.detach(), out.radii,
                             out.means2d_grad())

    def _clear_grads(self) -> None:
        """``optimizer.zero_grad(set_to_none=True)`` without its profiler hooks (a step's
        parameters are exactly ``self.params``, each in its own group)."""
        for p in self.params.values():
            p.grad = None

    def _finite(self, loss: float) -> bool:
        if not math.isfinite(loss):
            return False
        return all_finite([p.grad for p in self.params.values() if p.grad is not None])

    def _skip(self, view: int, loss: float) -> None:
        """Drop this step's gradients, count it, save what produced it; raise past the limit."""
        self._clear_grads()
        self.nonfinite_steps += 1
        saved = self._save_nonfinite_case(view, loss)
        where = f"saved to {saved}" if saved else "not saved (no folder given)"
        if self.nonfinite_steps > NONFINITE_STEP_LIMIT:
            raise NonFiniteTraining(
                f"training step {self.step} (view {view}): non-finite loss or gradient in "
                f"{self.nonfinite_steps} steps, more than the limit of {NONFINITE_STEP_LIMIT}; the "
                f"last case is {where}")

    def _save_nonfinite_case(self, view: int, loss: float) -> Path | None:
        """The parameters and camera of a skipped step, in the layout of the regression cases."""
        if self.nonfinite_dir is None:
            return None
        folder = Path(self.nonfinite_dir)
        folder.mkdir(parents=True, exist_ok=True)
        path = folder / f"nonfinite_step{self.step:06d}.pt"
        cams = self.cameras[view]
        torch.save({"gaussians": {k: v.detach().clone() for k, v in self.params.items()},
                    "viewmats": cams.viewmats, "Ks": cams.Ks, "width": cams.width,
                    "height": cams.height, "background": self.background, "target": self.images[view],
                    "sh_degree": self.active_sh_degree, "settings": repr(self.settings),
                    "step": self.step, "view": view, "loss": loss}, path)
        return path

    def gaussians_for_grad(self) -> Gaussians:
        """The parameters (leaves) as ``Gaussians``, not re-validated: they were at construction,
        and a step whose gradient is not finite never reaches them."""
        return Gaussians.unchecked(**self.params)

    def _density_control(self) -> None:
        """The recipe's density events of this step (``FitConfig.density_events``), none while
        ``train``'s ``settle`` holds them (its last steps); a held densification's gradient
        statistics carry on into the next one."""
        if self._settle_from is not None and self.step > self._settle_from:
            return
        dcfg = self.config.densify
        events = self.config.density_events(self.step)
        if "densify" in events:
            self.params = densify_and_prune(self.params, self.optimizer, self.stats, dcfg, self.extent,
                                            self.step > dcfg.prune_large_after, self.generator)
            self.stats = DensifyStats.zeros(self.params["means"].shape[0], self.stats.grad_sum)
        if "reset" in events:
            self.reset_opacity()

    def train(self, iterations: int, progress: bool = False, desc: str = "fit",
              on_step: Callable[[int, int, StepInfo], None] | None = None, settle: int = 0) -> StepInfo | None:
        """Run ``iterations`` steps; shows a progress bar (loss, PSNR, #Gaussians) if asked;
        ``on_step(done, iterations, info)`` hears every step (it decides how often to say so).
        ``settle``: no density event (densification, prune, periodic opacity reset) in the last
        ``settle`` of these steps, so what is evaluated after them has settled."""
        if settle < 0:
            raise ValueError(f"settle must be >= 0, got {settle}")
        self._settle_from = self.step + iterations - settle if settle else None
        try:
            return self._train(iterations, progress, desc, on_step)
        finally:
            self._settle_from = None

    def _train(self, iterations: int, progress: bool, desc: str,
               on_step: Callable[[int, int, StepInfo], None] | None) -> StepInfo | None:
        info = None
        bar = tqdm(total=iterations, desc=desc, disable=not progress, leave=False, mininterval=1.0)
        for done in range(1, iterations + 1):
            info = self.train_step()
            if on_step is not None:
                on_step(done, iterations, info)
            if info.step % 10 == 0:
                bar.set_postfix(loss=f"{info.loss:.4f}", psnr=f"{info.psnr:.2f}", n=info.num_gaussians,
                                refresh=False)
            bar.update(1)
        bar.close()
        return info


def fit(gaussians: Gaussians, cameras: Cameras, images: Tensor, config: FitConfig,
        background: Tensor | None = None, progress: bool = False) -> Gaussians:
    """Train from ``gaussians`` for ``config.iterations`` steps and return the fitted Gaussians."""
    trainer = Trainer(gaussians, cameras, images, config, background)
    trainer.train(config.iterations, progress=progress)
    return trainer.rendered_gaussians


@torch.no_grad()
def evaluate_psnr(gaussians: Gaussians, cameras: Cameras, images: Tensor,
                  background: Tensor | None = None) -> float:
    """Mean PSNR over views (each view's PSNR, then the mean, as 3DGS reports)."""
    values = [float(psnr(render(gaussians, cameras[i], background).rgb[0], images[i]))
              for i in range(len(cameras))]
    return sum(values) / len(values)
