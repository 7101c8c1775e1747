"""A method implemented outside gopre, reporting in gopre's tables: a worked example of the
``result.json`` format that imports nothing from the pipeline (numpy and Pillow only).

The "method" is deliberately trivial and honest about it: it takes the initial views, then the
pool views in id order up to the budget, and its "model" predicts every test view as the mean
colour of the views it took. Its PSNR per test image is computed here against the ground truth.

    python examples/external_result.py BENCHMARK.json SCENE_DIR --scene generated --seed 0 --out result.json
    gopre-report outputs/table2_goal --results result.json      # its row beside the sweep's
    (--renders also writes renders/<test_id>.png beside result.json: the report scores those itself)

Hashes follow gopre's convention (pipeline/interchange/hashes.py): a ground-truth image is the
sha256 of its file's bytes; a render the sha256 of its uint8 RGB pixels, [H, W, 3] in C order.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
from pathlib import Path

import numpy as np
from PIL import Image


def load_rgb(path: Path, width: int | None) -> np.ndarray:
    """[H, W, 3] in [0, 1]; RGBA over a white background (the Blender layout's), resized to width."""
    with Image.open(path) as im:
        im = im.convert("RGBA")
        if width is not None and im.width != width:
            im = im.resize((width, round(im.height * width / im.width)), Image.BICUBIC)
        rgba = np.asarray(im, dtype=np.float64) / 255.0
    return rgba[..., :3] * rgba[..., 3:] + (1.0 - rgba[..., 3:])


def frame_image(root: Path, file_path: str) -> Path:
    """A Blender frame's image: its file_path, with .png added when it names no image file."""
    path = root / file_path
    return path if path.suffix.lower() in (".png", ".jpg", ".jpeg") else path.with_name(path.name + ".png")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("benchmark", type=Path)
    parser.add_argument("scene_dir", type=Path)
    parser.add_argument("--scene", required=True)
    parser.add_argument("--seed", type=int, required=True)
    parser.add_argument("--protocol", default=None)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--renders", action="store_true",
                        help="also write each test view's render as renders/<test_id>.png beside --out "
                             "(gopre-report then scores the renders itself)")
    args = parser.parse_args(argv)
    doc = json.loads(args.benchmark.read_text())
    entries = [e for e in doc["entries"] if e["benchmark"]["scene"] == args.scene
               and e["benchmark"]["seed"] == args.seed
               and (args.protocol is None or e["benchmark"]["protocol"] == args.protocol)]
    if len(entries) != 1:
        parser.error(f"{len(entries)} benchmark entries match scene {args.scene} seed {args.seed}")
    entry = entries[0]
    views, width = entry["views"], entry["views"]["image_width"]
    for view, name in views["test_image_files"].items():  # the same ground truth, or stop here
        if hashlib.sha256((args.scene_dir / name).read_bytes()).hexdigest() != views["test_image_sha256"][view]:
            parser.error(f"{args.scene_dir / name}: not the benchmark's image (sha256 differs)")
    # the pool split's frames in file order (a Blender-layout scene: transforms_<split>.json)
    train = json.loads((args.scene_dir / f"transforms_{views['pool_split']}.json").read_text())["frames"]
    taken = list(views["initial_ids"])
    rounds = []
    for plan in entry["rounds"]:
        pick = [i for i in views["pool_ids"] if i not in taken][:plan["picks"]]
        rounds.append({"num_views": len(taken), "selected": pick})
        taken += pick
    colour = np.mean([load_rgb(frame_image(args.scene_dir, train[i]["file_path"]), width).mean((0, 1))
                      for i in taken], axis=0)
    per_image = []
    for view in views["test_ids"]:
        truth = load_rgb(args.scene_dir / views["test_image_files"][str(view)], width)
        pred = np.broadcast_to(colour, truth.shape)
        mse = float(np.mean((pred - truth) ** 2))
        pixels = np.floor(np.clip(pred, 0, 1) * 255 + 0.5).astype(np.uint8)
        if args.renders:
            (args.out.parent / "renders").mkdir(parents=True, exist_ok=True)
            Image.fromarray(pixels).save(args.out.parent / "renders" / f"{view}.png")
        per_image.append({"test_id": view, "psnr": -10 * math.log10(max(mse, 1e-12)),
                          "render_sha256": hashlib.sha256(np.ascontiguousarray(pixels).tobytes()).hexdigest()})
    rounds.append({"num_views": len(taken), "selected": []})
    result = {"schema": "gopre.result", "schema_version": 1,
              "method": {"name": "mean_colour", "strategy": "first_in_pool", "options": {}, "plugin": None},
              "benchmark": entry["benchmark"], "views": {k: v for k, v in views.items()},
              "rounds": rounds,
              "final": {"num_views": len(taken), "psnr": float(np.mean([p["psnr"] for p in per_image])),
                        "per_image": per_image},
              "code_version": "examples/external_result.py"}
    args.out.write_text(json.dumps(result, indent=1))
    print(f"wrote {args.out}: final PSNR {result['final']['psnr']:.2f} dB over {len(per_image)} test views")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
