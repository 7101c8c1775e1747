"""Training throughput: iterations per second of the CPU preset's fit (render, loss, backward,
Adam, densification statistics) on a random scene, per backend, in one process.

The trainer fits N random Gaussians to views rendered from a different random scene, with
densification moved past the run (its statistics are still gathered), so N stays fixed and every
backend does the same work. The backends' timed blocks are interleaved (block 1 of each backend,
then block 2, ...), so a change in the machine's load touches them alike; the figure is the
median block.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from dataclasses import replace

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


def _trainer(size: int, n: int) -> Trainer:
    cams, images = training_views(size, n)
    config = cpu_episode().fit.with_changes(image_width=size)  # the episodes' recipe
    config = config.with_changes(densify=replace(config.densify, start=10 ** 9))  # N stays fixed
    return Trainer(random_scene(n, seed=0, sh_degree=config.sh_degree), cams, images, config,
                   render_settings=RenderSettings(backend="auto"))


def iterations_per_second(backends: list[str], size: int, n: int, steps: int,
                          repeats: int) -> dict[str, tuple[float, float]]:
    """Per backend variant: (median over ``repeats`` interleaved blocks of ``steps`` iterations,
    after 5 warm-up iterations, in it/s; the peak RSS in MB over its warm-up iterations)."""
    trainers, peaks = {b: _trainer(size, n) for b in backends}, {}
    for backend in backends:
        reset_peak_rss()
        with backend_variant(backend):
            for _ in range(5):
                trainers[backend].train_step()
        peaks[backend] = peak_rss_mb()
    rates: dict[str, list[float]] = {b: [] for b in backends}
    for _ in range(repeats):
        for backend in backends:
            with backend_variant(backend):
                start = time.perf_counter()
                for _ in range(steps):
                    trainers[backend].train_step()
                rates[backend].append(steps / (time.perf_counter() - start))
    return {b: (statistics.median(rates[b]), peaks[b]) for b in backends}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(prog="python -m pipeline.bench train", description=__doc__)
    parser.add_argument("--size", type=int, default=64)
    parser.add_argument("--gaussians", type=int, default=10000)
    parser.add_argument("--steps", type=int, default=50, help="iterations per timed block")
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--backends", nargs="+", default=["tiles", "compiled-unfused", "compiled"],
                        choices=BACKEND_VARIANTS,
                        help="compiled-unfused: the compiled ops without the fused training "
                             "render (the path before it), for a before/after in one process")
    args = parser.parse_args(argv)
    rates = iterations_per_second(args.backends, args.size, args.gaussians, args.steps,
                                  args.repeats)
    for backend, (rate, peak) in rates.items():
        print(json.dumps({"backend": backend, "width": args.size, "n_gaussians": args.gaussians,
                          "its_per_s": round(rate, 2),
                          "speedup_vs_torch": (round(rate / rates["tiles"][0], 2)
                                               if "tiles" in rates else None),
                          "peak_rss_mb": round(peak, 1), "steps": args.steps,
                          "repeats": args.repeats, "threads": torch.get_num_threads(),
                          "load_avg_1m": round(machine_load(), 2)}), flush=True)
