"""``gopre-data``: inspect a dataset folder, or generate the default scene.

    gopre-data inspect PATH [--deep]   JSON summary; exits 1 with a message naming the file on bad data
                                          (--deep: decode every image, as a sweep will)
    gopre-data generate OUT [--seed S] [--size W]
    gopre-data twin SCENE OUT.ply [--width W] [--iterations N] [--seed S]
                                       the digital twin for world=twin: a splat trained on every
                                       training view (test views held out), its PSNR on both
    gopre-data capture PHOTOS_DIR|VIDEO --out SCENE [--max-size PX] [--frames N] [--up METHOD|X,Y,Z]
                                       structure-from-motion (pycolmap, CPU) of your own photos or
                                       video into a COLMAP scene (undistorted, masks kept), with
                                       SCENE/capture.json: registered images, points, reprojection error
    gopre-data cameras SCENE --out FIG.png [--up METHOD|X,Y,Z]
                                       the scene's cameras from above and the side, its goal sector
    gopre-data geometry SCENE [--images DIR] [--every N]
                                       the geometry check: an evenly spaced subset reconstructed with
                                       exhaustive matching, aligned to the model's cameras; exits 3 when
                                       the model is folded or drifted, 4 when no subset registered enough
    gopre-data benchmark PRESET [KEY=VALUE ...] --out FILE
                                       the preset's benchmark definitions: per (scene, seed) the initial
                                       views, pool, goal probes per round, test views with image hashes
                                       and the budget, as JSON (pipeline/interchange/benchmark.schema.json)
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from pipeline.cli import alias_note, command_name, unwritable
from pipeline.data.images import DataError
from pipeline.data.load import load_scene
from pipeline.data.synthetic import at_fraction


def summary(path: Path, deep: bool = False) -> dict:
    scene = load_scene(path)
    first = next(iter(scene.splits.values()))
    out = {"path": str(path), "format": scene.format, "name": scene.name,
           "splits": {k: len(v) for k, v in scene.splits.items()},
           "image_size": [first.cameras.width, first.cameras.height],
           "camera_model": {"blender": "PINHOLE (from camera_angle_x)", "colmap": "from COLMAP",
                            "nerfstudio": "from transforms.json"}.get(scene.format, scene.format)
                           + (" (undistorted, cached)" if scene.info.get("undistorted") else ""),
           "traits": {"kind": scene.traits.kind, "up": scene.traits.up, "split": scene.traits.split},
           "points": 0 if scene.points is None else int(len(scene.points))}
    if scene.traits.up != "z" or scene.info.get("up") is not None:  # an estimated up axis: every estimate
        from pipeline.data.orientation import orientation
        out["orientation"] = orientation(scene.all_cameras(), scene.points, scene.info.get("up")).to_dict()
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


def write_benchmark(preset: str, overrides: list[str], out: Path) -> dict:
    """Compose ``experiment=preset`` with ``overrides`` as gopre-run would, and write the
    benchmark definitions of its episodes (validated against the schema) to ``out``."""
    from hydra import compose, initialize_config_dir
    from hydra.errors import HydraException
    from omegaconf import OmegaConf

    from pipeline.cli.run import CONF_DIR, register_resolvers
    from pipeline.experiment.episode_settings import ConfigError
    from pipeline.experiment.build import expand_jobs
    from pipeline.experiment.provenance import code_version
    from pipeline.experiment.result_document import benchmark_document, benchmark_entries
    from pipeline.experiment.executors import scene_key
    from pipeline.experiment.sweep import prepare_scenes
    from pipeline.interchange.documents import validate
    register_resolvers()
    try:
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            cfg = compose("config", overrides=[f"experiment={preset}", *overrides])
    except HydraException as err:
        raise ValueError(f"experiment={preset} {' '.join(overrides)}: {err}") from None
    OmegaConf.resolve(cfg)
    try:
        jobs = expand_jobs(cfg)
        scenes, errors = prepare_scenes(jobs)
    except ConfigError as err:
        raise ValueError(str(err)) from None
    if errors:
        raise ValueError("; ".join(errors))
    command = " ".join(["gopre-data benchmark", preset, *overrides, "--out", str(out)])
    doc = validate(benchmark_document(preset, benchmark_entries(jobs, scenes, scene_key), code_version(), command),
                   "benchmark", str(out))
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(doc, indent=1) + "\n")
    except OSError as err:
        raise ValueError(f"--out {out}: cannot write it ({err.strerror or err})") from None
    return {"written": str(out), "preset": preset, "entries": len(doc["entries"])}


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
    cap = sub.add_parser("capture", help="photos or a video in, a COLMAP scene out (pycolmap SfM on the CPU)")
    cap.add_argument("source", type=Path, help="a folder of photos (masks/ beside it is kept) or a video file")
    cap.add_argument("--out", type=Path, required=True, help="the scene folder to create (must be new or empty)")
    cap.add_argument("--max-size", type=int, default=800, help="longest side of the images SfM sees (default 800)")
    cap.add_argument("--frames", type=int, default=100, help="video: how many sharp frames to keep (default 100)")
    cap.add_argument("--keep-work", action="store_true", help="keep the SfM database and logs (OUT/_capture_work)")
    cap.add_argument("--matcher", default="auto", choices=("auto", "exhaustive", "loop", "sequential"),
                     help="auto (the default): exhaustive up to 200 photos, else the walk's neighbours plus a "
                          "skeleton, matched again exhaustively when that model fails the geometry check")
    cap.add_argument("--up", default=None, metavar="METHOD|X,Y,Z",
                     help="the scene's up axis: cameras (the mean camera up; the default), plane (the points' "
                          "dominant plane), pca (the camera centres' smallest axis) or a vector; kept in capture.json")
    figure = sub.add_parser("cameras", help="a figure of a scene's cameras and its goal sector (no images)")
    figure.add_argument("scene", type=Path)
    figure.add_argument("--out", type=Path, required=True, help="the figure file (.png or .pdf)")
    figure.add_argument("--up", default=None, metavar="METHOD|X,Y,Z", help="draw it about this up axis")
    geo = sub.add_parser("geometry", help="check a COLMAP or nerfstudio model for a fold or drift: an evenly spaced "
                                          "subset reconstructed with exhaustive matching, aligned to its cameras")
    geo.add_argument("scene", type=Path, help="a scene folder (or a bare COLMAP model folder with --images)")
    geo.add_argument("--images", type=Path, default=None, help="the folder of the model's images (default SCENE/images)")
    geo.add_argument("--every", type=int, default=5, help="every Nth photo in name order (default 5; larger when "
                                                          "the subset would exceed 80 photos)")
    bench = sub.add_parser("benchmark", help="write a preset's benchmark definitions (views a method must use)")
    bench.add_argument("preset", help="an experiment preset, e.g. table2_goal")
    bench.add_argument("overrides", nargs="*", help="gopre-run overrides, e.g. 'dataset=[generated]' splat=cpu")
    bench.add_argument("--out", type=Path, required=True, help="the JSON file to write")
    args = parser.parse_args(argv)
    try:
        if args.command == "capture":
            from pipeline.data.capture import capture_scene
            made = capture_scene(args.source, args.out, args.max_size, args.frames,
                                 progress=lambda line: print(line, file=sys.stderr, flush=True),
                                 keep_work=args.keep_work, up=args.up, matcher=args.matcher)
            print(json.dumps(made.to_dict()))
            print(f"{made.registered}/{made.images} images registered, {made.points} points, "
                  f"{made.mean_reprojection_error_px:.2f} px mean reprojection error, {made.seconds['total']:.0f} s; "
                  f"scene: {made.out} (capture.json)", file=sys.stderr)
            return 0
        if args.command == "cameras":
            from pipeline.cli.scene_figure import camera_figure
            print(json.dumps(camera_figure(args.scene, args.out, up_choice=args.up)))
            return 0
        if args.command == "geometry":
            from pipeline.data.geometry_check import check_geometry
            check = check_geometry(args.scene, args.images, args.every,
                                   say=lambda line: print(line, file=sys.stderr, flush=True))
            print(json.dumps(check.to_dict()))
            print(("the model is FOLDED OR DRIFTED: " if check.folded else "") + check.line(), file=sys.stderr)
            return 3 if check.folded else 4 if check.verdict == "inconclusive" else 0
        if args.command == "benchmark":
            print(json.dumps(write_benchmark(args.preset, args.overrides, args.out)))
            return 0
        if args.command == "inspect":
            print(json.dumps(summary(args.path, args.deep)))
        elif args.command == "twin":
            print(json.dumps(make_twin(args.scene, args.out, args.width, args.iterations, args.seed)))
        else:
            from pipeline.data.synthetic import generate
            problem = unwritable(args.out, "OUT", folder=True)
            if problem:
                raise ValueError(problem)
            out = generate(args.out, seed=args.seed, size=args.size, progress=print_progress)
            print(json.dumps({"written": str(out), "seed": args.seed, "size": args.size}))
    except (DataError, ValueError) as err:
        print(f"{command_name('data')}: error: {err}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
