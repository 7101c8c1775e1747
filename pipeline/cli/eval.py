"""``gopre-eval``: score any 3DGS PLY with this pipeline's metrics (nerfstudio's ``ns-eval``).

    gopre-eval MODEL.ply SCENE                       the protocol's test views (global: the
                                                        Blender test split / every 8th COLMAP view)
    gopre-eval MODEL.ply SCENE --protocol goal       the test views in the 120-degree sector
    gopre-eval MODEL.ply SCENE --width 64 --out metrics.json
    gopre-eval --sweep outputs/science                  fill in what a sweep's episodes were recorded
                                                        without: the 3DGS SSIM (metrics version 1), the
                                                        final model's pixel-level uncertainty, camera
                                                        path and (generated scene) depth errors

MODEL is an INRIA-layout PLY (ours, gsplat's, INRIA's, nerfstudio's export); SCENE a Blender or
COLMAP folder. The model is rendered at the scene's cameras scaled to ``--width`` (default: the
images' own width) over the scene's background, and PSNR, SSIM and LPIPS (when its weights are
installed; otherwise "unavailable", never a number) are computed per view and averaged, exactly
as episodes are scored. Prints one JSON object on one line (also written, indented, to ``--out``).
SSIM is 3DGS's (zero-padded windows, the mean over all pixels), ``ssim_skimage`` scikit-image's.

``--sweep DIR`` renders each finished episode's final model (``jobs/<hash>/artifacts/model.ply``)
on its test views, checks that it reproduces the recorded PSNR and scikit-image SSIM, and writes
the 3DGS SSIM into the job's result.json and the sweep's records.parquet (``--data-root``: where
the scenes are when the sweep was copied from another machine); then, for each episode recorded
without the final model's uncertainty, it measures it as a job does today (the model must reproduce
the recorded PSNR first) and writes it the same way. See ``pipeline.experiment.fill_metrics``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from pipeline.cli import alias_note, command_name, unwritable
from pipeline.data.images import DataError
from pipeline.data.protocols import KINDS
from pipeline.eval.model import evaluate_model
from pipeline.experiment.fill_metrics import fill_ssim, fill_uncertainty


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog=command_name("eval"), description=__doc__,
                                     epilog=alias_note("eval"),
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("model", type=Path, nargs="?", help="a 3DGS PLY")
    parser.add_argument("scene", type=Path, nargs="?", help="a Blender or COLMAP scene folder")
    parser.add_argument("--sweep", type=Path, default=None,
                        help="a sweep folder: fill in the metrics its episodes were recorded without")
    parser.add_argument("--data-root", default=None, help="--sweep: where its scenes are now")
    parser.add_argument("--protocol", default="global", choices=KINDS)
    parser.add_argument("--width", type=int, default=None, help="render and compare at this width")
    parser.add_argument("--llff-hold", type=int, default=8, help="COLMAP: every n-th view is a test view")
    parser.add_argument("--no-lpips", action="store_true")
    parser.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    args = parser.parse_args(argv)
    if args.sweep is not None:
        if args.model is not None or args.scene is not None:
            parser.error("--sweep DIR takes no MODEL or SCENE")
        return fill_sweep(args.sweep, args.data_root)
    if args.model is None or args.scene is None:
        parser.error("MODEL and SCENE are required (or --sweep DIR)")
    if args.width is not None and args.width < 1:
        parser.error(f"--width: expected a positive integer, got {args.width}")
    problem = unwritable(args.out, "--out") if args.out is not None else None
    if problem:
        print(f"{command_name('eval')}: error: {problem}", file=sys.stderr)
        return 1
    try:
        result = evaluate_model(args.model, args.scene, args.protocol, args.width, not args.no_lpips,
                                args.llff_hold)
    except (DataError, ValueError, FileNotFoundError) as err:
        print(f"{command_name('eval')}: error: {err}", file=sys.stderr)
        return 1
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps(result))  # one line: what scripts parse
    return 0


def fill_sweep(folder: Path, data_root: str | None) -> int:
    try:
        ssim = fill_ssim(folder, data_root, progress=print)
        print(f"{folder}: 3DGS SSIM: {ssim.summary()}")
        uncertainty = fill_uncertainty(folder, data_root, progress=print)
        print(f"{folder}: uncertainty, camera path, depth: {uncertainty.summary()}")
    except (DataError, ValueError, FileNotFoundError) as err:
        print(f"{command_name('eval')}: error: {err}", file=sys.stderr)
        return 1
    return 1 if ssim.refused or uncertainty.refused else 0


if __name__ == "__main__":
    sys.exit(main())
