"""Episode benchmark: one full active-reconstruction episode, timed.

    python -m pipeline.bench episode --scene PATH --strategy NAME [--preset cpu] [--seed 0]

Prints one JSON line with ``wall_s, final_psnr, final_ssim, final_lpips, selected`` and the
per-round curve and selection times. Target: the Blender 10-view episode (2 initial views, +1 per
round) at the CPU preset on lego in <= 15 minutes on 2 cores.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch

from pipeline.active import episode_preset, run_episode
from pipeline.bench.measure import BACKEND_VARIANTS, backend_variant, machine_load
from pipeline.data.load import load_scene
from pipeline.data.protocols import ProtocolConfig
from pipeline.experiment.provenance import numeric_paths


def main(argv=None) -> list[dict]:
    parser = argparse.ArgumentParser(prog="python -m pipeline.bench episode", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scene", type=Path, required=True)
    parser.add_argument("--strategy", required=True)
    parser.add_argument("--preset", default="cpu", choices=["cpu", "paper", "tiny"])
    parser.add_argument("--protocol", default="global", choices=["global", "goal", "sparse"])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--checkpoint", type=Path, default=None, help="resume folder")
    parser.add_argument("--progress", action="store_true")
    parser.add_argument("--backends", nargs="+", default=["compiled"], choices=BACKEND_VARIANTS,
                        help="run the episode once per backend (add tiles for speedup_vs_torch; "
                             "compiled-unfused: the compiled path without its fused paths, the "
                             "before of a before/after, with same_as_first saying whether the "
                             "picks and the final PSNR agree)")
    args = parser.parse_args(argv)
    rows: list[dict] = []
    torch_wall = None
    for backend in args.backends:
        with backend_variant(backend):
            row = run_one(args, backend)
        if backend == "tiles":
            torch_wall = row["wall_s"]
        row["speedup_vs_torch"] = round(torch_wall / row["wall_s"], 2) if torch_wall else None
        if rows:
            first = rows[0]
            row["speedup_vs_first"] = round(first["wall_s"] / row["wall_s"], 2)
            row["same_as_first"] = {"picks": row["selected"] == first["selected"],
                                    "final_psnr_diff_db": round(row["final_psnr_full"]
                                                                - first["final_psnr_full"], 6)}
        print(json.dumps(row), flush=True)
        rows.append(row)
    return rows


def run_one(args, backend: str) -> dict:
    start = time.perf_counter()
    cfg = episode_preset(args.preset, strategy=args.strategy, seed=args.seed)
    cfg = cfg.with_changes(protocol=ProtocolConfig(**{**cfg.protocol.__dict__, "kind": args.protocol}))
    scene = load_scene(args.scene, width=cfg.fit.image_width)
    checkpoint = args.checkpoint
    if checkpoint is not None and len(args.backends) > 1:  # one resume folder per backend
        checkpoint = checkpoint / backend
    result = run_episode(scene, cfg, checkpoint, progress=args.progress)
    return {"scene": str(args.scene), "strategy": args.strategy, "backend": backend,
            "preset": args.preset, "protocol": args.protocol, "seed": args.seed,
            "wall_s": round(time.perf_counter() - start, 1),
            "final_psnr": round(result.final.psnr, 3), "final_psnr_full": result.final.psnr,
            "final_ssim": None if result.final.ssim is None else round(result.final.ssim, 4),
            "final_lpips": result.final.lpips, "lpips_status": result.final.lpips_status,
            "selected": result.selected, "initial": result.initial,
            "curve": [[r.num_views, round(r.test_psnr, 3)] for r in result.rounds],
            "selection_s": [r.selection_seconds for r in result.rounds[:-1]],
            "selection_total_s": round(sum(r.selection_seconds for r in result.rounds), 1),
            "train_s": round(sum(r.train_seconds for r in result.rounds), 1),
            "num_gaussians": result.final.num_gaussians, "threads": torch.get_num_threads(),
            "load_avg_1m": round(machine_load(), 2), "numerics": numeric_paths()}


if __name__ == "__main__":
    main()
