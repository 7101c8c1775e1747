"""``pipeline-eval``: score any 3DGS PLY with this pipeline's metrics (nerfstudio's ``ns-eval``).

    pipeline-eval MODEL.ply SCENE                       the protocol's test views (global: the
                                                        Blender test split / every 8th COLMAP view)
    pipeline-eval MODEL.ply SCENE --protocol goal       the test views in the 120-degree sector
    pipeline-eval MODEL.ply SCENE --width 64 --out metrics.json

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

from pipeline.data.images import DataError
from pipeline.data.load import load_scene
from pipeline.data.protocols import KINDS, ProtocolConfig, build_protocol
from pipeline.eval.metrics import LpipsMetric, evaluate_views
from pipeline.splat import ply


def evaluate_model(model: Path, scene_path: Path, protocol: str = "global", width: int | None = None,
                   lpips: bool = True, llff_hold: int = 8) -> dict:
    """The metrics of ``model`` on the test views of ``scene_path`` under ``protocol``."""
    gaussians = ply.load(model)
    scene = load_scene(scene_path, width=width)
    # only the test views matter here: the smallest schedule, so any pool size is accepted
    views = build_protocol(scene, ProtocolConfig(kind=protocol, llff_hold=llff_hold, initial_views=1,
                                                 budget=2))
    test = scene.split(views.test_split)
    ids = list(views.test_ids)
    cameras = test.cameras[ids]
    metric = LpipsMetric() if lpips else None
    m = evaluate_views(gaussians, cameras, test.images.stack(ids), scene.background.to(gaussians.means), metric)
    return {"model": str(model), "scene": str(scene_path), "protocol": protocol,
            "test_split": views.test_split, "test_views": len(ids), "width": cameras.width,
            "height": cameras.height, "num_gaussians": len(gaussians), "sh_degree": gaussians.sh_degree,
            **m.mean(), "lpips_status": m.lpips_status if lpips else "LPIPS not requested",
            "ssim_convention": "scikit-image structural_similarity (valid interior), as the episodes",
            "per_view": [{"id": i, "psnr": p, "ssim": s} for i, p, s in zip(ids, m.psnr, m.ssim)]}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="pipeline-eval", description=__doc__,
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
        print(f"pipeline-eval: error: {err}", file=sys.stderr)
        return 1
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps(result))  # one line: what scripts parse
    return 0


if __name__ == "__main__":
    sys.exit(main())
