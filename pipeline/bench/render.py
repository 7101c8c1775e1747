"""Renderer benchmark: the compiled backend and the torch tile path (and the dense oracle), forward
and forward+backward; peak RSS is measured per backend (the peak since that backend started)."""

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


def time_backend(gaussians, cams, backend: str, repeats: int) -> dict:
    settings = RenderSettings(backend=backend)
    reset_peak_rss()
    with torch.no_grad():
        fwd = median_seconds(lambda: render(gaussians, cams, settings=settings), repeats)
    fb = median_seconds(fwd_bwd(gaussians, cams, settings), repeats)
    return {"fwd_s": fwd, "fwd_bwd_s": fb, "peak_rss_mb": peak_rss_mb()}


def dense_seconds(gaussians, cams, size: int, n: int, repeats: int, max_dense_pairs: float):
    """(seconds or None, checkpointed, skipped reason) of the dense oracle's fwd+bwd."""
    dense_need_mb = size * size * n * DENSE_BYTES_PER_PAIR / 2 ** 20
    block = None
    budget_mb = 0.5 * available_memory_mb()
    if dense_need_mb > budget_mb:  # checkpoint pixel blocks; a second forward runs in backward
        block = int(budget_mb * 2 ** 20 / (n * DENSE_BYTES_PER_PAIR * 2))
    if size * size * n > max_dense_pairs:
        return None, block is not None, "pairs > --max-dense-pairs"
    if block is not None and block < 256:
        return None, True, "too little memory"
    settings = RenderSettings(backend="dense", dense_pixel_block=block)
    dense_repeats = 1 if size * size * n > 5e7 else max(1, repeats // 2)  # slow: seconds+
    return median_seconds(fwd_bwd(gaussians, cams, settings), dense_repeats, warmup=0), \
        block is not None, None


def bench_case(size: int, n: int, repeats: int, seed: int = 0, max_dense_pairs: float = 3e8,
               backends=("tiles", "compiled")) -> list[dict]:
    """One JSON row per backend; ``speedup_vs_torch`` = the torch path's (``tiles``) fwd+bwd time
    over this backend's, both measured here on the same scene."""
    gaussians = random_scene(n, seed=seed).requires_grad_()
    cams = orbit_cameras(1, size, size)
    times = {b: time_backend(gaussians, cams, b, repeats) for b in backends}
    dense, checkpointed, skipped = dense_seconds(gaussians, cams, size, n, repeats, max_dense_pairs)
    torch_fb = times["tiles"]["fwd_bwd_s"] if "tiles" in times else None
    rows = []
    for backend, t in times.items():
        rows.append({"backend": backend, "width": size, "height": size, "n_gaussians": n,
                     "fwd_s": round(t["fwd_s"], 4), "fwd_bwd_s": round(t["fwd_bwd_s"], 4),
                     "speedup_vs_torch": None if torch_fb is None else round(torch_fb / t["fwd_bwd_s"], 2),
                     "fwd_speedup_vs_torch": (None if torch_fb is None else
                                              round(times["tiles"]["fwd_s"] / t["fwd_s"], 2)),
                     "dense_fwd_bwd_s": None if dense is None else round(dense, 4),
                     "speedup_vs_dense": None if dense is None else round(dense / t["fwd_bwd_s"], 1),
                     "dense_checkpointed": checkpointed, "dense_skipped": skipped,
                     "peak_rss_mb": round(t["peak_rss_mb"], 1), "repeats": repeats,
                     "threads": torch.get_num_threads(), "load_avg_1m": round(machine_load(), 2)})
    return rows


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(prog="python -m pipeline.bench render", description=__doc__)
    parser.add_argument("--sizes", type=int, nargs="+", default=[64, 100, 200])
    parser.add_argument("--gaussians", type=int, nargs="+", default=[5000, 20000, 50000])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--max-dense-pairs", type=float, default=3e8,
                        help="skip the dense oracle above this many pixel x Gaussian pairs (slow)")
    parser.add_argument("--backends", nargs="+", default=["tiles", "compiled"],
                        choices=["tiles", "compiled"])
    args = parser.parse_args(argv)
    for size in args.sizes:
        for n in args.gaussians:
            for row in bench_case(size, n, args.repeats, max_dense_pairs=args.max_dense_pairs,
                                  backends=args.backends):
                print(json.dumps(row), flush=True)
