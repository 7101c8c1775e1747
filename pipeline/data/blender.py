"""NeRF-synthetic ("Blender") reader: transforms_{train,val,test}.json + RGBA PNGs.

Camera conversion: the JSON holds camera-to-world matrices in the OpenGL/Blender camera frame
(x right, y up, looking down -z); OpenCV is x right, y down, z forward, so columns 1 and 2 of
the rotation are negated before inverting. focal = 0.5 W / tan(0.5 camera_angle_x) with W the
width of the actual image files, principal point at the image centre.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import torch

from pipeline.cameras import Cameras
from pipeline.data.images import DataError, ImageStore, image_size
from pipeline.data.scene import Scene, Split

SPLITS = ("train", "val", "test")


def _load_json(path: Path) -> dict:
    try:
        with open(path) as f:
            data = json.load(f)
    except json.JSONDecodeError as err:
        raise DataError(f"{path}: malformed JSON ({err.msg} at line {err.lineno})") from None
    if not isinstance(data, dict) or "frames" not in data or "camera_angle_x" not in data:
        raise DataError(f"{path}: expected an object with 'camera_angle_x' and 'frames'")
    if not isinstance(data["frames"], list) or not data["frames"]:
        raise DataError(f"{path}: split has no frames")
    return data


def _frame_path(root: Path, json_path: Path, frame: dict, index: int) -> Path:
    if "file_path" not in frame or "transform_matrix" not in frame:
        raise DataError(f"{json_path}: frame {index} lacks 'file_path' or 'transform_matrix'")
    rel = frame["file_path"]
    path = (root / rel).resolve()
    if path.suffix.lower() not in (".png", ".jpg", ".jpeg"):
        path = path.with_name(path.name + ".png")
    if not path.exists():
        raise DataError(f"{json_path}: frame {index} image {path} does not exist")
    return path


def c2w_opengl_to_viewmat(c2w) -> torch.Tensor:
    """[C, 4, 4] OpenGL camera-to-world -> OpenCV world-to-camera."""
    c2w = torch.as_tensor(c2w, dtype=torch.float64).clone()
    c2w[:, :3, 1:3] *= -1
    return torch.linalg.inv(c2w)


def read_blender(root: str | Path, width: int | None = None, background=(1.0, 1.0, 1.0),
                 splits=SPLITS, budget_mb: float = 1024.0) -> Scene:
    """Read a Blender-layout scene; images are resized to ``width`` (None = as stored)."""
    root = Path(root)
    if not root.is_dir():
        raise DataError(f"{root}: scene folder does not exist")
    bg = torch.tensor(background, dtype=torch.float32)
    out: dict[str, Split] = {}
    for split in splits:
        json_path = root / f"transforms_{split}.json"
        if not json_path.exists():
            if split == "train":
                raise DataError(f"{json_path}: missing (a Blender scene needs transforms_train.json)")
            continue
        data = _load_json(json_path)
        paths = [_frame_path(root, json_path, f, i) for i, f in enumerate(data["frames"])]
        sizes = {image_size(p) for p in paths[:1] + paths[-1:]}
        if len(sizes) != 1:
            raise DataError(f"{json_path}: images of inconsistent size {sorted(sizes)}")
        full_w, full_h = sizes.pop()
        w = width or full_w
        h = round(full_h * w / full_w)
        focal = 0.5 * w / math.tan(0.5 * float(data["camera_angle_x"]))
        try:
            c2w = torch.tensor([f["transform_matrix"] for f in data["frames"]], dtype=torch.float64)
        except (TypeError, ValueError):
            raise DataError(f"{json_path}: a transform_matrix is not a 4x4 list of numbers") from None
        if c2w.shape[1:] != (4, 4):
            raise DataError(f"{json_path}: transform_matrix must be 4x4, got {list(c2w.shape[1:])}")
        bad = (~torch.isfinite(c2w).all(dim=2).all(dim=1)).nonzero()[:, 0].tolist()
        if bad:
            frame = data["frames"][bad[0]]
            raise DataError(f"{json_path}: frame {bad[0]} ({frame['file_path']}): transform_matrix contains "
                            f"NaN or inf" + (f" ({len(bad)} frames in all)" if len(bad) > 1 else ""))
        k = torch.tensor([[focal, 0, w / 2], [0, focal, h / 2], [0, 0, 1]], dtype=torch.float64)
        cams = Cameras(c2w_opengl_to_viewmat(c2w).float(), k.expand(len(paths), 3, 3).float(), w, h)
        names = [Path(f["file_path"]).name for f in data["frames"]]
        out[split] = Split(cams, ImageStore(paths, (w, h), bg, budget_mb, (full_w, full_h)), names)
    box = (torch.full((3,), -1.3), torch.full((3,), 1.3))  # 3DGS's random init for synthetic scenes
    return Scene(root.name, "blender", root, out, bg, box=box)
