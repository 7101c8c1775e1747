"""Exact diagonal Fisher benchmark: time of one view's Fisher vs one fwd+bwd of the same view."""

from __future__ import annotations

import argparse
import json

import torch

from pipeline.bench.measure import machine_load, median_seconds, peak_rss_mb, reset_peak_rss
from pipeline.fisher.exact import view_fisher
from pipeline.splat import RenderSettings, render
from pipeline.splat.scenes import orbit_cameras, random_scene


def bench_case(size: int, n: int, repeats: int, backends=("tiles", "compiled")) -> list[dict]:
    """One row per backend: its per-view Fisher against its own fwd+bwd of the same view;
    ``speedup_vs_torch`` = the torch path's Fisher time over this backend's (same process, scene)."""
    gaussians = random_scene(n, seed=0)
    cams = orbit_cameras(1, size, size)
    leaves = gaussians.clone().requires_grad_()
    times = {}
    for backend in backends:
        settings = RenderSettings(backend=backend)

        def fwd_bwd():
            render(leaves, cams, settings=settings).rgb.sum().backward()
        reset_peak_rss()
        fb = median_seconds(fwd_bwd, repeats)
        fisher = median_seconds(lambda: view_fisher(gaussians, cams, settings=settings), repeats)
        times[backend] = (fisher, fb, peak_rss_mb())
    torch_fisher = times["tiles"][0] if "tiles" in times else None
    return [{"backend": backend, "width": size, "height": size, "n_gaussians": n,
             "fisher_s": round(fisher, 4), "fwd_bwd_s": round(fb, 4), "ratio": round(fisher / fb, 2),
             "speedup_vs_torch": None if torch_fisher is None else round(torch_fisher / fisher, 2),
             "peak_rss_mb": round(peak, 1), "repeats": repeats, "threads": torch.get_num_threads(),
             "load_avg_1m": round(machine_load(), 2)}
            for backend, (fisher, fb, peak) in times.items()]


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(prog="python -m pipeline.bench fisher", description=__doc__)
    parser.add_argument("--sizes", type=int, nargs="+", default=[100, 200])
    parser.add_argument("--gaussians", type=int, nargs="+", default=[20000, 50000])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--backends", nargs="+", default=["tiles", "compiled"],
                        choices=["tiles", "compiled"])
    args = parser.parse_args(argv)
    for size in args.sizes:
        for n in args.gaussians:
            for row in bench_case(size, n, args.repeats, args.backends):
                print(json.dumps(row), flush=True)
