"""Exact diagonal Fisher benchmark: time of one view's Fisher vs one fwd+bwd of the same view."""

from __future__ import annotations

import argparse
import json

import torch

from pipeline.bench.measure import machine_load, median_seconds, peak_rss_mb, reset_peak_rss
from pipeline.fisher.exact import view_fisher
from pipeline.splat import render
from pipeline.splat.scenes import orbit_cameras, random_scene


def bench_case(size: int, n: int, repeats: int) -> dict:
    gaussians = random_scene(n, seed=0)
    cams = orbit_cameras(1, size, size)
    leaves = gaussians.clone().requires_grad_()

    def fwd_bwd():
        render(leaves, cams).rgb.sum().backward()
    reset_peak_rss()
    fb = median_seconds(fwd_bwd, repeats)
    fisher = median_seconds(lambda: view_fisher(gaussians, cams), repeats)
    return {"width": size, "height": size, "n_gaussians": n, "fisher_s": round(fisher, 4),
            "fwd_bwd_s": round(fb, 4), "ratio": round(fisher / fb, 2),
            "peak_rss_mb": round(peak_rss_mb(), 1), "repeats": repeats,
            "threads": torch.get_num_threads(), "load_avg_1m": round(machine_load(), 2)}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(prog="python -m pipeline.bench fisher", description=__doc__)
    parser.add_argument("--sizes", type=int, nargs="+", default=[100, 200])
    parser.add_argument("--gaussians", type=int, nargs="+", default=[20000, 50000])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args(argv)
    for size in args.sizes:
        for n in args.gaussians:
            print(json.dumps(bench_case(size, n, args.repeats)), flush=True)
