"""nerfstudio's capture layout (``ns-process-data``): one ``transforms.json``.

Intrinsics ``fl_x fl_y cx cy w h`` at the top level or per frame (a frame's own win), distortion
``k1 k2 p1 p2`` (OPENCV; ``k3``/``k4`` non-zero is refused: not a model COLMAP's undistorter takes
as OPENCV), ``frames[].file_path`` and ``frames[].transform_matrix`` (camera-to-world, OpenGL axes as
the Blender layout's), optional ``frames[].mask_path`` (white = kept) and ``applied_transform`` (the
transform nerfstudio already applied to the poses: the poses are used as written, in that frame).
A fisheye or equirectangular ``camera_model`` is refused by name. Frames are taken in file-name
order; the split is the LLFF hold-out (every 8th frame is a test view), as for COLMAP scenes.
A model with distortion is written as a COLMAP model and undistorted with COLMAP's undistorter into
the cache (``colmap.undistorted_copy``), never into the user's folder.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import torch

from pipeline.cameras import Cameras
from pipeline.data.blender import c2w_opengl_to_viewmat
from pipeline.data.images import DataError, ImageStore, image_size
from pipeline.data.scene import Scene, Split

REFUSED_MODELS = ("OPENCV_FISHEYE", "FISHEYE", "EQUIRECTANGULAR")
INTRINSICS = ("fl_x", "fl_y", "cx", "cy", "w", "h")
DISTORTION = ("k1", "k2", "p1", "p2")


def load_transforms(root: Path) -> dict:
    path = root / "transforms.json"
    try:
        meta = json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise DataError(f"{path}: malformed JSON ({err})") from None
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list) or not meta["frames"]:
        raise DataError(f"{path}: expected an object with a non-empty 'frames' list")
    model = str(meta.get("camera_model", "OPENCV")).upper()
    if model in REFUSED_MODELS:
        raise DataError(f"{path}: camera_model {model} is not supported (pinhole cameras with OPENCV "
                        "distortion only: re-run ns-process-data with --camera-type perspective)")
    return meta


def _frame_camera(meta: dict, frame: dict, path: Path, index: int) -> dict:
    cam = {}
    for key in (*INTRINSICS, *DISTORTION, "k3", "k4"):
        value = frame.get(key, meta.get(key))
        if value is None and key in INTRINSICS:
            raise DataError(f"{path}: frame {index} ({frame.get('file_path')}) has no {key!r} (nor the file)")
        cam[key] = float(value or 0.0)
    if cam["k3"] or cam["k4"]:
        raise DataError(f"{path}: frame {index} has k3/k4 distortion ({cam['k3']}, {cam['k4']}); only OPENCV's "
                        "k1 k2 p1 p2 are supported")
    return cam


def _image_path(root: Path, rel: str, path: Path, index: int) -> Path:
    image = (root / rel).resolve()
    if not image.exists():
        raise DataError(f"{path}: frame {index} image {image} does not exist")
    return image


def frame_viewmats(frames: list[dict], path: Path) -> torch.Tensor:
    """[C, 4, 4] float64 world->camera (OpenCV) of the frames' camera-to-world ``transform_matrix``
    (OpenGL axes; 4x4, or 3x4 without the last row)."""
    c2w = torch.tensor(np.array([f["transform_matrix"] for f in frames], dtype=np.float64))
    if c2w.shape[1:] not in ((4, 4), (3, 4)):
        raise DataError(f"{path}: transform_matrix must be 4x4 (or 3x4), got {tuple(c2w.shape[1:])}")
    if c2w.shape[1] == 3:
        c2w = torch.cat([c2w, torch.tensor([0, 0, 0, 1.0], dtype=torch.float64).expand(len(c2w), 1, 4)], 1)
    return c2w_opengl_to_viewmat(c2w)


def read_nerfstudio(root: str | Path, width: int | None = None, masks: bool = False, llff_hold: int = 8,
                    background=(0.0, 0.0, 0.0)) -> Scene:
    root = Path(root)
    path = root / "transforms.json"
    meta = load_transforms(root)
    for i, frame in enumerate(meta["frames"]):
        if "file_path" not in frame or "transform_matrix" not in frame:
            raise DataError(f"{path}: frame {i} lacks 'file_path' or 'transform_matrix'")
    frames = sorted(meta["frames"], key=lambda f: str(f["file_path"]))
    cams = [_frame_camera(meta, f, path, i) for i, f in enumerate(frames)]
    images = [_image_path(root, f["file_path"], path, i) for i, f in enumerate(frames)]
    mask_files = None
    if masks:
        missing = [f["file_path"] for f in frames if not f.get("mask_path")]
        if missing:
            raise DataError(f"{path}: masks were asked for but {len(missing)} frame(s) have no mask_path: "
                            f"{', '.join(missing[:5])}")
        mask_files = [_image_path(root, f["mask_path"], path, i) for i, f in enumerate(frames)]
    if any(c[k] for c in cams for k in DISTORTION):
        return _undistorted(root, frames, cams, images, mask_files, width, llff_hold, background)
    sizes = {(c["w"], c["h"]) for c in cams}
    if len(sizes) > 1:
        raise DataError(f"{path}: frames of different sizes {sorted(sizes)[:3]}: one image size per scene")
    model_w, model_h = sizes.pop()
    file_w, file_h = image_size(images[0])
    w = width or file_w
    h = round(file_h * w / file_w)
    sx, sy = w / model_w, h / model_h
    ks = torch.tensor([[[c["fl_x"] * sx, 0, c["cx"] * sx], [0, c["fl_y"] * sy, c["cy"] * sy], [0, 0, 1]]
                       for c in cams], dtype=torch.float32)
    cameras = Cameras(frame_viewmats(frames, path).float(), ks, w, h)
    bg = torch.tensor(background, dtype=torch.float32)
    names = [f["file_path"] for f in frames]
    store = ImageStore(images, (w, h), bg, source_size=(file_w, file_h))
    test = [i for i in range(len(names)) if i % llff_hold == 0]
    train = [i for i in range(len(names)) if i % llff_hold != 0]
    splits = {"all": Split(cameras, store, names),
              "train": Split(cameras[train], store.subset(train), [names[i] for i in train]),
              "test": Split(cameras[test], store.subset(test), [names[i] for i in test])}
    masks_of = None if mask_files is None else {
        "all": mask_files, "train": [mask_files[i] for i in train], "test": [mask_files[i] for i in test]}
    return Scene(root.name, "nerfstudio", root, splits, bg, info={"transforms": str(path)}, masks=masks_of)


def colmap_text_model(frames: list[dict], cams: list[dict], names: list[str], sparse: Path) -> None:
    """The frames as a COLMAP text model (one OPENCV camera per frame, world-to-camera poses in
    OpenCV axes, no points), for COLMAP's undistorter."""
    from scipy.spatial.transform import Rotation
    sparse.mkdir(parents=True)
    viewmats = frame_viewmats(frames, sparse).numpy()
    camera_lines, image_lines = [], []
    for i, (cam, vm, name) in enumerate(zip(cams, viewmats, names), start=1):
        params = [cam[k] for k in ("fl_x", "fl_y", "cx", "cy", "k1", "k2", "p1", "p2")]
        camera_lines.append(f"{i} OPENCV {int(cam['w'])} {int(cam['h'])} " + " ".join(_num(p) for p in params))
        x, y, z, w = Rotation.from_matrix(vm[:3, :3]).as_quat()
        pose = [w, x, y, z, *vm[:3, 3]]
        image_lines.append(f"{i} " + " ".join(_num(p) for p in pose) + f" {i} {name}\n")
    (sparse / "cameras.txt").write_text("\n".join(camera_lines) + "\n")
    (sparse / "images.txt").write_text("\n".join(image_lines) + "\n")
    (sparse / "points3D.txt").write_text("")


def _num(value) -> str:
    return f"{float(value):.17g}"


def _undistorted(root: Path, frames, cams, images, mask_files, width, llff_hold, background) -> Scene:
    """A distorted capture: written as a COLMAP model beside links to its images in a staging folder
    of the cache, undistorted there (``colmap.undistorted_copy``) and read as a COLMAP scene."""
    from pipeline.data.colmap import cache_root, read_colmap, undistorted_copy
    names = [f"{k:05d}{Path(p).suffix.lower()}" for k, p in enumerate(images)]  # file-name order kept
    staging = cache_root() / f"{root.name}-nerfstudio-source"
    shutil.rmtree(staging, ignore_errors=True)
    try:
        (staging / "images").mkdir(parents=True)
        for name, image in zip(names, images):
            (staging / "images" / name).symlink_to(image)
        if mask_files is not None:
            (staging / "masks").mkdir()
            for name, mask in zip(names, mask_files):
                (staging / "masks" / f"{Path(name).stem}.png").symlink_to(mask)
        colmap_text_model(frames, cams, names, staging / "sparse" / "0")
        copy = undistorted_copy(root, staging / "sparse" / "0", staging / "images",
                                staging / "masks" if mask_files is not None else None)
    except OSError as err:
        raise DataError(f"{root}: cannot stage the undistortion under {cache_root()} ({err}); "
                        "set GOPRE_CACHE to a writable folder") from None
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    scene = read_colmap(copy, width, "images", background, llff_hold, False, masks=mask_files is not None)
    scene.name, scene.root, scene.format = root.name, root, "nerfstudio"
    scene.info["undistorted"] = str(copy)
    for split in scene.splits.values():  # the frames' own names, as transforms.json gives them
        split.names = [frames[int(Path(n).stem)]["file_path"] for n in split.names]
    return scene
