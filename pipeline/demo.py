"""The main job on the embedded default: generate the scene, fit a splat, report held-out PSNR.

    python -m pipeline.demo [--out outputs/demo] [--views 20] [--iterations 1000] [--width 64]

Outputs (git-ignored) under --out: the generated scene, ``result.json`` and ``renders.png``
(ground truth above, renders below, for a few held-out views).
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from pipeline.data.blender import read_blender
from pipeline.data.synthetic import generate
from pipeline.fit import Trainer, cpu_preset, evaluate_psnr
from pipeline.fit.init import random_in_box
from pipeline.splat import render


def ensure_scene(folder: Path, seed: int, size: int) -> Path:
    if not (folder / "transforms_test.json").exists():
        print(f"generating the default scene into {folder} (300 views at {size}x{size}) ...", flush=True)
        generate(folder, seed=seed, size=size)
    return folder


def save_strip(path: Path, gt: torch.Tensor, pred: torch.Tensor) -> None:
    rows = [torch.cat(list(x), dim=1) for x in (gt, pred.clamp(0, 1))]
    img = (torch.cat(rows, dim=0).numpy() * 255 + 0.5).astype(np.uint8)
    Image.fromarray(img).save(path)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("outputs/demo"))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--size", type=int, default=100, help="generated image size")
    parser.add_argument("--width", type=int, default=64, help="training resolution")
    parser.add_argument("--views", type=int, default=20, help="training views (uniform subset)")
    parser.add_argument("--test-views", type=int, default=20)
    parser.add_argument("--iterations", type=int, default=1000)
    parser.add_argument("--max-gaussians", type=int, default=10_000)
    args = parser.parse_args(argv)
    torch.manual_seed(args.seed)
    start = time.time()
    scene = read_blender(ensure_scene(args.out / "scene", args.seed, args.size), width=args.width)
    train, test = scene.split("train"), scene.split("test")
    idx = np.linspace(0, len(train) - 1, args.views).round().astype(int).tolist()
    test_idx = np.linspace(0, len(test) - 1, args.test_views).round().astype(int).tolist()
    base = cpu_preset()
    scaled = base.scaled_to(args.iterations)
    cfg = scaled.with_changes(seed=args.seed,
                              densify=replace(scaled.densify, max_gaussians=args.max_gaussians))
    lo, hi = scene.bounds()
    init = random_in_box(cfg.init_points, lo, hi, cfg.sh_degree, seed=args.seed)
    trainer = Trainer(init, train.cameras[idx], train.images.stack(idx), cfg, scene.background)
    trainer.train(cfg.iterations, progress=True, desc="fitting")
    gaussians = trainer.gaussians
    test_imgs = test.images.stack(test_idx)
    result = {
        "scene": str(args.out / "scene"), "train_views": len(idx), "test_views": len(test_idx),
        "iterations": cfg.iterations, "width": args.width, "num_gaussians": len(gaussians),
        "train_psnr": round(evaluate_psnr(gaussians, train.cameras[idx], train.images.stack(idx),
                                          scene.background), 2),
        "test_psnr": round(evaluate_psnr(gaussians, test.cameras[test_idx], test_imgs,
                                         scene.background), 2),
        "wall_s": round(time.time() - start, 1),
    }
    with torch.no_grad():
        shown = test_idx[:6]
        pred = render(gaussians, test.cameras[shown], scene.background).rgb
    save_strip(args.out / "renders.png", test.images.stack(shown), pred)
    (args.out / "result.json").write_text(json.dumps(result, indent=1))
    print(json.dumps(result))
    print(f"held-out PSNR {result['test_psnr']} dB on {len(test_idx)} test views; "
          f"renders in {args.out / 'renders.png'}")
    return result


if __name__ == "__main__":
    main()
