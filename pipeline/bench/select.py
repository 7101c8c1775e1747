"""Selection benchmark: one round of each strategy over a candidate pool.

Also times the bare Fisher pass over the candidates. ``scoring_overhead`` is the part of a round
spent outside Fisher passes relative to the Fisher passes it made (candidates, the taken views
for H_train, and for gopre the K probes for M); ``overhead_vs_bare_fisher`` compares the whole
round with the bare candidate pass, so it includes the probes' Fisher.
"""

from __future__ import annotations

import argparse
import json
import time

import torch

from pipeline.acquisition import SelectionContext, make_strategy
from pipeline.bench.measure import (BACKEND_VARIANTS, backend_variant, machine_load, peak_rss_mb,
                                    reset_peak_rss)
from pipeline.fisher.exact import FisherSpec, view_fisher
from pipeline.splat.scenes import random_scene, sphere_cameras

STRATEGIES = ("random", "coverage", "fisherrf", "popgs", "gopre")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(prog="python -m pipeline.bench select", description=__doc__)
    parser.add_argument("--candidates", type=int, default=100)
    parser.add_argument("--size", type=int, default=100)
    parser.add_argument("--gaussians", type=int, default=20000)
    parser.add_argument("--taken", type=int, default=2)
    parser.add_argument("--probes", type=int, default=25)
    parser.add_argument("--strategies", nargs="+", default=list(STRATEGIES))
    parser.add_argument("--backends", nargs="+", default=["tiles", "compiled"],
                        choices=BACKEND_VARIANTS,
                        help="each strategy's round is run on each; speedup_vs_torch compares them "
                             "(compiled-unfused: the compiled path without its fused paths)")
    args = parser.parse_args(argv)
    g = random_scene(args.gaussians, seed=0)
    pool = sphere_cameras(args.candidates, args.size, args.size, seed=1)
    taken = sphere_cameras(args.taken, args.size, args.size, seed=2)
    probes = sphere_cameras(args.probes, args.size, args.size, seed=3)
    torch_round = {}
    for backend in args.backends:
        with backend_variant(backend):
            start = time.perf_counter()
            view_fisher(g, pool, torch.ones(3), FisherSpec())
            bare = (time.perf_counter() - start) / args.candidates
            for name in args.strategies:
                row = select_row(name, backend, args, g, pool, taken, probes, bare)
                if backend == "tiles":
                    torch_round[name] = row["round_s"]
                row["speedup_vs_torch"] = (round(torch_round[name] / row["round_s"], 2)
                                           if name in torch_round and row["round_s"] > 0 else None)
                print(json.dumps(row), flush=True)


def select_row(name, backend, args, g, pool, taken, probes, bare) -> dict:
    reset_peak_rss()
    ctx = SelectionContext(g, pool, list(range(args.candidates)), taken, torch.ones(3),
                           torch.Generator().manual_seed(0), probes)
    sel = make_strategy(name).select(ctx)
    return {"strategy": name, "backend": backend, "candidates": args.candidates, "width": args.size,
            "n_gaussians": args.gaussians, "per_candidate_ms": round(sel.seconds_per_candidate * 1e3, 2),
            "round_s": round(sel.round_seconds, 3), "peak_rss_mb": round(peak_rss_mb(), 1),
            "bare_fisher_per_candidate_ms": round(bare * 1e3, 2),
            "overhead_vs_bare_fisher": round(sel.seconds_per_candidate / bare - 1, 3),
            "fisher_views": sel.fisher_views,
            "scoring_overhead": (round((sel.round_seconds - sel.fisher_seconds) / sel.fisher_seconds, 4)
                                 if sel.fisher_seconds else None),
            "threads": torch.get_num_threads(), "load_avg_1m": round(machine_load(), 2)}
