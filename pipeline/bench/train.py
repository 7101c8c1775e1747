"""Training throughput: iterations per second of the CPU preset's fit (render, loss, backward,
Adam, densification statistics) on a random scene, per backend, in one process.

The trainer fits N random Gaussians to views rendered from a different random scene; the timed
iterations are taken before densification starts, so N stays fixed and every backend does the
same work.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import torch

from pipeline.bench.measure import (BACKEND_VARIANTS, backend_variant, machine_load, peak_rss_mb,
                                    reset_peak_rss)
from pipeline.active.config import cpu_episode
from pipeline.fit.trainer import Trainer
from pipeline.splat import RenderSettings, render
from pipeline.splat.scenes import orbit_cameras, random_scene


def training_views(size: int, n: int, views: int = 8):
    """(cameras, images [C, H, W, 3]) of a random target scene."""
    cams = orbit_cameras(views, size, size)
    with torch.no_grad():
        images = render(random_scene(n, seed=1), cams, settings=RenderSettings(backend="tiles")).rgb
    return cams, images.clamp(0, 1)


def iterations_per_second(backend: str, size: int, n: int, steps: int, repeats: int) -> float:
    """Median over ``repeats`` blocks of ``steps`` iterations (after 2 warm-up iterations)."""
    cams, images = training_views(size, n)
    config = cpu_episode().fit.with_changes(image_width=size)  # the episodes' recipe
    trainer = Trainer(random_scene(n, seed=0, sh_degree=config.sh_degree), cams, images, config,
                      render_settings=RenderSettings(backend=backend))
    if steps * repeats + 2 >= config.densify.start:
        raise ValueError(f"--steps x --repeats must stay below the densification start "
                         f"({config.densify.start})")
    for _ in range(2):
        trainer.train_step()
    rates = []
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(steps):
            trainer.train_step()
        rates.append(steps / (time.perf_counter() - start))
    return statistics.median(rates)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(prog="python -m pipeline.bench train", description=__doc__)
    parser.add_argument("--size", type=int, default=64)
    parser.add_argument("--gaussians", type=int, default=10000)
    parser.add_argument("--steps", type=int, default=20, help="iterations per timed block")
    parser.add_argument("--repeats", type=int, default=4)  # 2 + 20 x 4 < densify.start (100)
    parser.add_argument("--backends", nargs="+", default=["tiles", "compiled-unfused", "compiled"],
                        choices=BACKEND_VARIANTS,
                        help="compiled-unfused: the compiled ops without the fused training "
                             "render (the path before it), for a before/after in one process")
    args = parser.parse_args(argv)
    rates = {}
    for backend in args.backends:
        reset_peak_rss()
        with backend_variant(backend):
            rate = iterations_per_second("auto", args.size, args.gaussians, args.steps, args.repeats)
        rates[backend] = (rate, peak_rss_mb())
    for backend, (rate, peak) in rates.items():
        print(json.dumps({"backend": backend, "width": args.size, "n_gaussians": args.gaussians,
                          "its_per_s": round(rate, 2),
                          "speedup_vs_torch": (round(rate / rates["tiles"][0], 2)
                                               if "tiles" in rates else None),
                          "peak_rss_mb": round(peak, 1), "steps": args.steps,
                          "repeats": args.repeats, "threads": torch.get_num_threads(),
                          "load_avg_1m": round(machine_load(), 2)}), flush=True)
