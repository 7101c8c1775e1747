"""An outside model scored like an episode: any 3DGS PLY on a scene's (or a protocol's) test views,
with the episodes' own PSNR / SSIM / LPIPS. The ``gopre-eval`` command is ``pipeline.cli.eval``."""

from __future__ import annotations

from pathlib import Path

from pipeline.data.load import load_scene
from pipeline.data.protocols import ProtocolConfig, build_protocol
from pipeline.eval.metrics import SSIM_CONVENTION, LpipsMetric, evaluate_views
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
            "ssim_convention": SSIM_CONVENTION,
            "per_view": [{"id": i, "psnr": p, "ssim": s, "ssim_skimage": k}
                         for i, p, s, k in zip(ids, m.psnr, m.ssim, m.ssim_skimage)]}
