"""The digital twin of a scene: a reference splat trained on every training view of the
scene (the global protocol's initial and pool views; its test views held out), the capture
simulator of ``world=twin``. Views captured off the dataset's poses are the twin's renders."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from pipeline.active.config import cpu_episode
from pipeline.active.episode import initial_gaussians
from pipeline.data.protocols import ProtocolConfig, build_protocol
from pipeline.data.scene import Scene
from pipeline.eval.metrics import evaluate_views
from pipeline.splat import Gaussians
from pipeline.world import train_twin


@dataclass
class Twin:
    gaussians: Gaussians
    train_views: int
    train_psnr: float       # mean over the views it was trained on
    test_views: int
    test_psnr: float        # mean over the protocol's held-out test views (real photographs)
    iterations: int


def build_twin(scene: Scene, iterations: int, seed: int = 0, progress: bool = False) -> Twin:
    """Train the twin with the CPU recipe rescaled to ``iterations`` at the scene's loaded width."""
    if iterations < 1:
        raise ValueError(f"iterations must be >= 1, got {iterations}")
    views = build_protocol(scene, ProtocolConfig(kind="global"))
    pool = scene.split(views.pool_split)
    ids = sorted(set(views.initial_ids) | set(views.pool_ids))
    cfg = cpu_episode(seed=seed)
    cfg = cfg.with_changes(fit=cfg.fit.scaled_to(iterations).with_changes(image_width=pool.cameras.width, seed=seed))
    torch.manual_seed(seed)
    g = train_twin(initial_gaussians(scene, cfg), pool.cameras[ids], pool.images.stack(ids), cfg.fit,
                   scene.background, progress=progress)
    test = scene.split(views.test_split)
    train_m = evaluate_views(g, pool.cameras[ids], pool.images.stack(ids), scene.background, ssim=False)
    test_m = evaluate_views(g, test.cameras[views.test_ids], test.images.stack(views.test_ids),
                            scene.background, ssim=False)
    return Twin(g, len(ids), float(train_m.mean()["psnr"]), len(views.test_ids), float(test_m.mean()["psnr"]),
                iterations)
