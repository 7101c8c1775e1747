"""``gopre-eval``: score any 3DGS PLY with this pipeline's metrics (nerfstudio's ``ns-eval``).

    gopre-eval MODEL.ply SCENE                       the protocol's test views (global: the
                                                        Blender test split / every 8th COLMAP view)
    gopre-eval MODEL.ply SCENE --protocol goal       the test views in the 120-degree sector
    gopre-eval MODEL.ply SCENE --width 64 --out metrics.json

MODEL is an INRIA-layout PLY (ours, gsplat's, INRIA's, nerfstudio's export); SCENE a Blender or
COLMAP folder. The model is rendered at the scene's cameras scaled to ``--width`` (default: the
images' own width) over the scene's background, and PSNR, SSIM and LPIPS (when its weights are
installed; otherwise "unavailable", never a number) are computed per view and averaged, exactly
as episodes are scored. Prints one JSON object on one line (also written, indented, to ``--out``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from pipeline.cli import alias_note, command_name
from pipeline.data.images import DataError
from pipeline.data.protocols import KINDS
from pipeline.eval.model import evaluate_model


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog=command_name("eval"), description=__doc__,
                                     epilog=alias_note("eval"),
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("model", type=Path, help="a 3DGS PLY")
    parser.add_argument("scene", type=Path, help="a Blender or COLMAP scene folder")
    parser.add_argument("--protocol", default="global", choices=KINDS)
    parser.add_argument("--width", type=int, default=None, help="render and compare at this width")
    parser.add_argument("--llff-hold", type=int, default=8, help="COLMAP: every n-th view is a test view")
    parser.add_argument("--no-lpips", action="store_true")
    parser.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    args = parser.parse_args(argv)
    if args.width is not None and args.width < 1:
        parser.error(f"--width: expected a positive integer, got {args.width}")
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


if __name__ == "__main__":
    sys.exit(main())
