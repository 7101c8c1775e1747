"""``gopre-data``: inspect a dataset folder, or generate the default scene.

    gopre-data inspect PATH [--deep]   JSON summary; exits 1 with a message naming the file on bad data
                                          (--deep: decode every image, as a sweep will)
    gopre-data generate OUT [--seed S] [--size W]
    gopre-data twin SCENE OUT.ply [--width W] [--iterations N] [--seed S]
                                       the digital twin for world=twin: a splat trained on every
                                       training view (test views held out), its PSNR on both
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from pipeline.cli import alias_note, command_name
from pipeline.data.images import DataError
from pipeline.data.load import load_scene
from pipeline.data.synthetic import at_fraction


def summary(path: Path, deep: bool = False) -> dict:
    scene = load_scene(path)
    first = next(iter(scene.splits.values()))
    out = {"path": str(path), "format": scene.format, "name": scene.name,
           "splits": {k: len(v) for k, v in scene.splits.items()},
           "image_size": [first.cameras.width, first.cameras.height],
           "camera_model": "PINHOLE (from camera_angle_x)" if scene.format == "blender" else "from COLMAP",
           "points": 0 if scene.points is None else int(len(scene.points))}
    if scene.format == "colmap":
        out["model_image_size"] = scene.info.get("model_size")
    first.images[0]  # decode one image: a broken file fails here, naming it
    if deep:  # every image of every split: unreadable files and wrong sizes fail here, named
        for split in scene.splits.values():
            for i in range(len(split.images)):
                split.images[i]
        out["images_checked"] = sum(len(s.images) for s in scene.splits.values())
    return out


def print_progress(split: str, done: int, total: int) -> None:
    """One line per tenth of a split (stderr, so stdout stays the JSON summary)."""
    if at_fraction(done, total, 10):
        print(f"{split}: {done}/{total} views", file=sys.stderr, flush=True)


def make_twin(scene_path: Path, out: Path, width: int, iterations: int, seed: int) -> dict:
    from pipeline.active.twin import build_twin
    from pipeline.splat import ply
    if width < 8:
        raise ValueError(f"--width must be at least 8 pixels, got {width}")
    twin = build_twin(load_scene(scene_path, width=width), iterations, seed, progress=False)
    written = ply.save(twin.gaussians, out)
    return {"written": str(written), "use": f"world=twin world.model=ply:{written}", "width": width,
            "iterations": iterations, "gaussians": len(twin.gaussians), "train_views": twin.train_views,
            "train_psnr": round(twin.train_psnr, 3), "test_views": twin.test_views,
            "test_psnr": round(twin.test_psnr, 3),
            "note": "views captured off the dataset's poses are this twin's renders, not photographs"}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog=command_name("data"), description=__doc__,
                                     epilog=alias_note("data"),
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    inspect = sub.add_parser("inspect", help="print a JSON summary of a scene folder")
    inspect.add_argument("path", type=Path)
    inspect.add_argument("--deep", action="store_true", help="decode every image (slower)")
    gen = sub.add_parser("generate", help="write the generated default scene (Blender layout)")
    gen.add_argument("out", type=Path)
    gen.add_argument("--seed", type=int, default=0)
    gen.add_argument("--size", type=int, default=100)
    twin = sub.add_parser("twin", help="train the scene's digital twin (world=twin) and save it as PLY")
    twin.add_argument("scene", type=Path)
    twin.add_argument("out", type=Path)
    twin.add_argument("--width", type=int, default=64, help="training width in pixels (default 64)")
    twin.add_argument("--iterations", type=int, default=5000)
    twin.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    try:
        if args.command == "inspect":
            print(json.dumps(summary(args.path, args.deep)))
        elif args.command == "twin":
            print(json.dumps(make_twin(args.scene, args.out, args.width, args.iterations, args.seed)))
        else:
            from pipeline.data.synthetic import generate
            out = generate(args.out, seed=args.seed, size=args.size, progress=print_progress)
            print(json.dumps({"written": str(out), "seed": args.seed, "size": args.size}))
    except (DataError, ValueError) as err:
        print(f"{command_name('data')}: error: {err}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
