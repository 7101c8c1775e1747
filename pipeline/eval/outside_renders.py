"""An outside ``result.json`` that ships its renders: the metrics recomputed from the pixels.

A result may ship the final model's render of every test view as ``renders/<test_id>.png`` beside
the file (8-bit RGB, the size of the benchmark's working width). Each render must be the pixels its
``per_image[].render_sha256`` names (gopre's convention, ``pipeline.interchange.hashes``), else the
result is refused naming the file and the view. The PSNR (and 3DGS's SSIM) of each render is then
computed here against the ground truth as gopre's own episodes read it (the scene's reader at the
working width), so an outside method is scored on equal terms whatever resize or background its
own code used; the report uses these values and says how far the file's own were from them.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from pipeline.data.scene import Scene
from pipeline.eval.metrics import psnr_value, ssim_value
from pipeline.interchange.documents import DocumentError
from pipeline.interchange.hashes import pixels_sha256

RENDERS = "renders"


@dataclass(frozen=True)
class RecomputedMetrics:
    """Per test view (the result's order): PSNR and SSIM from the shipped renders, and the largest
    difference from the file's own PSNR."""

    psnr: list[float]
    ssim: list[float]
    largest_psnr_gap_db: float


def shipped_renders(result_path: str | Path) -> Path | None:
    """The renders folder beside a result file, None when it ships none."""
    folder = Path(result_path).parent / RENDERS
    return folder if folder.is_dir() else None


def read_render(path: Path) -> np.ndarray:
    """[H, W, 3] uint8 of a shipped render (an error naming the file when it is not an RGB image)."""
    try:
        with Image.open(path) as im:
            im.load()
            return np.asarray(im.convert("RGB"), dtype=np.uint8)
    except OSError as err:
        raise DocumentError(f"{path}: cannot read the render ({err})") from None


def recompute(doc: dict, result_path: str | Path, scene: Scene) -> RecomputedMetrics:
    """Check every shipped render against its hash and score it against the scene's ground truth."""
    folder = shipped_renders(result_path)
    if folder is None:
        raise DocumentError(f"{result_path}: no {RENDERS}/ folder beside it")
    test = scene.split(doc["views"]["test_split"])
    psnrs, ssims, gap = [], [], 0.0
    for item in doc["final"]["per_image"]:
        view = int(item["test_id"])
        path = folder / f"{view}.png"
        if not path.is_file():
            raise DocumentError(f"{result_path}: {RENDERS}/{view}.png is missing (a result that ships renders "
                                "ships one per test view)")
        pixels = read_render(path)
        if item.get("render_sha256") and pixels_sha256(pixels) != item["render_sha256"]:
            raise DocumentError(f"{path}: its pixels are not final.per_image's render_sha256 for test view {view}")
        truth = test.images[view]  # [H, W, 3] as the episodes read it
        if tuple(truth.shape[:2]) != pixels.shape[:2]:
            raise DocumentError(f"{path}: {pixels.shape[1]}x{pixels.shape[0]} px, the benchmark's test view {view} is "
                                f"{truth.shape[1]}x{truth.shape[0]} at its working width")
        render = torch.from_numpy(pixels.astype(np.float32) / 255.0)
        psnrs.append(psnr_value(render, truth))
        ssims.append(ssim_value(render, truth))
        gap = max(gap, abs(psnrs[-1] - float(item["psnr"])))
    return RecomputedMetrics(psnrs, ssims, gap)
