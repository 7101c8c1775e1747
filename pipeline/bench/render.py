"""Renderer benchmark: tiled fast path vs the dense oracle, forward and forward+backward."""

from __future__ import annotations

import argparse
import json

import torch

from pipeline.bench.measure import (available_memory_mb, machine_load, median_seconds, peak_rss_mb,
                                    reset_peak_rss)
from pipeline.splat import RenderSettings, render
from pipeline.splat.scenes import orbit_cameras, random_scene

# Measured peak of the dense oracle's forward+backward, bytes per (pixel, Gaussian) pair, float32
DENSE_BYTES_PER_PAIR = 80


def fwd_bwd(gaussians, cams, settings):
    def run():
        out = render(gaussians, cams, settings=settings)
        out.rgb.sum().backward()
    return run


def bench_case(size: int, n: int, repeats: int, seed: int = 0, max_dense_pairs: float = 3e8) -> dict:
    gaussians = random_scene(n, seed=seed).requires_grad_()
    cams = orbit_cameras(1, size, size)
    tiles = RenderSettings(backend="tiles")
    reset_peak_rss()
    with torch.no_grad():
        fwd = median_seconds(lambda: render(gaussians, cams, settings=tiles), repeats)
    fb = median_seconds(fwd_bwd(gaussians, cams, tiles), repeats)
    peak = peak_rss_mb()
    dense_need_mb = size * size * n * DENSE_BYTES_PER_PAIR / 2 ** 20
    dense, block = None, None
    budget_mb = 0.5 * available_memory_mb()
    if dense_need_mb > budget_mb:  # checkpoint pixel blocks; a second forward runs in backward
        block = int(budget_mb * 2 ** 20 / (n * DENSE_BYTES_PER_PAIR * 2))
    too_slow = size * size * n > max_dense_pairs
    if not too_slow and (block is None or block >= 256):
        dense_settings = RenderSettings(backend="dense", dense_pixel_block=block)
        dense_repeats = 1 if size * size * n > 5e7 else max(1, repeats // 2)  # slow: seconds+
        dense = median_seconds(fwd_bwd(gaussians, cams, dense_settings), dense_repeats, warmup=0)
    return {"width": size, "height": size, "n_gaussians": n, "fwd_s": round(fwd, 4),
            "fwd_bwd_s": round(fb, 4), "dense_fwd_bwd_s": None if dense is None else round(dense, 4),
            "speedup_vs_dense": None if dense is None else round(dense / fb, 1),
            "dense_checkpointed": block is not None,
            "dense_skipped": "pairs > --max-dense-pairs" if too_slow else None,
            "peak_rss_mb": round(peak, 1), "repeats": repeats, "threads": torch.get_num_threads(),
            "load_avg_1m": round(machine_load(), 2)}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(prog="python -m pipeline.bench render", description=__doc__)
    parser.add_argument("--sizes", type=int, nargs="+", default=[64, 100, 200])
    parser.add_argument("--gaussians", type=int, nargs="+", default=[5000, 20000, 50000])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--max-dense-pairs", type=float, default=3e8,
                        help="skip the dense oracle above this many pixel x Gaussian pairs (slow)")
    args = parser.parse_args(argv)
    for size in args.sizes:
        for n in args.gaussians:
            print(json.dumps(bench_case(size, n, args.repeats, max_dense_pairs=args.max_dense_pairs)),
                  flush=True)
