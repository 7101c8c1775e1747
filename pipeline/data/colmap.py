"""COLMAP reader (Mip-NeRF360, Tanks & Temples): a sparse model read with pycolmap, binary or text.

Cameras: PINHOLE, SIMPLE_PINHOLE, SIMPLE_RADIAL and OPENCV. Images are expected undistorted: a
model with non-zero distortion is refused with a message saying so (pass allow_distortion=True
to use it anyway, ignoring the distortion). The image folder may hold any resolution (images_N,
or a downsampled copy): intrinsics are rescaled from the actual size of the files. COLMAP's
pixel convention (image corner at 0, first pixel centre at 0.5) is ours, so scaling is exact.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from pipeline.cameras import Cameras
from pipeline.data.images import DataError, ImageStore, image_size
from pipeline.data.scene import Scene, Split

SUPPORTED = {"PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "OPENCV"}


# COLMAP camera model id -> number of parameters (src/colmap/sensor/models.h)
MODEL_PARAMS = {0: 3, 1: 4, 2: 4, 3: 5, 4: 8, 5: 8, 6: 12, 7: 5, 8: 4, 9: 5, 10: 12}


def check_cameras_bin(path: Path) -> None:
    """The binary camera file is complete: its declared cameras, each (id, model, width, height,
    parameters), fill it exactly. pycolmap reads a truncated file without an error."""
    import struct
    data = path.read_bytes()
    try:
        (count,) = struct.unpack_from("<Q", data, 0)
        offset = 8
        for _ in range(count):
            _, model, width, height = struct.unpack_from("<iiQQ", data, offset)
            if model not in MODEL_PARAMS or not (0 < width < 1 << 20 and 0 < height < 1 << 20):
                raise DataError(f"{path}: malformed COLMAP camera file (camera model {model}, "
                                f"size {width}x{height} at byte {offset})")
            offset += 24 + 8 * MODEL_PARAMS[model]
    except struct.error:
        raise DataError(f"{path}: truncated COLMAP camera file ({len(data)} bytes)") from None
    if offset > len(data):
        raise DataError(f"{path}: truncated COLMAP camera file ({len(data)} bytes, {offset} needed)")


def _sparse_dir(root: Path) -> Path:
    for candidate in (root / "sparse" / "0", root / "sparse"):
        if (candidate / "cameras.bin").exists() or (candidate / "cameras.txt").exists():
            return candidate
    raise DataError(f"{root}: no COLMAP model (expected sparse/0/cameras.bin or cameras.txt)")


def _intrinsics(cam, path: Path, allow_distortion: bool) -> tuple[float, float, float, float]:
    model = cam.model.name if hasattr(cam.model, "name") else str(cam.model)
    p = [float(x) for x in cam.params]
    if model not in SUPPORTED:
        raise DataError(f"{path}: camera {cam.camera_id} has unsupported model {model}; supported: "
                        f"{sorted(SUPPORTED)} (undistort the images with COLMAP first)")
    if model == "PINHOLE":
        fx, fy, cx, cy, dist = p[0], p[1], p[2], p[3], []
    elif model == "SIMPLE_PINHOLE":
        fx, fy, cx, cy, dist = p[0], p[0], p[1], p[2], []
    elif model == "SIMPLE_RADIAL":
        fx, fy, cx, cy, dist = p[0], p[0], p[1], p[2], p[3:]
    else:  # OPENCV: fx, fy, cx, cy, k1, k2, p1, p2
        fx, fy, cx, cy, dist = p[0], p[1], p[2], p[3], p[4:]
    if any(abs(d) > 0 for d in dist) and not allow_distortion:
        raise DataError(f"{path}: camera {cam.camera_id} ({model}) has non-zero distortion {dist}; "
                        "undistorted images are expected (run COLMAP's image_undistorter)")
    return fx, fy, cx, cy


# 3DGS's resolution rule: without an explicit width, images wider than 1600 px train at 1600 px.
MAX_DEFAULT_WIDTH = 1600


def read_colmap(root: str | Path, width: int | None = None, images: str = "images",
                background=(0.0, 0.0, 0.0), llff_hold: int = 8, allow_distortion: bool = False,
                budget_mb: float = 1024.0) -> Scene:
    """Read a COLMAP scene; images resized to ``width`` (None = as stored in ``images``, but at
    most ``MAX_DEFAULT_WIDTH`` px wide, 3DGS's rule).

    Splits: ``train`` and ``test`` by the LLFF hold-out (every ``llff_hold``-th image in name
    order is a test view), and ``all`` in name order.
    """
    import pycolmap

    root = Path(root)
    if not root.is_dir():
        raise DataError(f"{root}: scene folder does not exist")
    sparse = _sparse_dir(root)
    if (sparse / "cameras.bin").exists():
        check_cameras_bin(sparse / "cameras.bin")
    try:
        rec = pycolmap.Reconstruction(str(sparse))
    except Exception as err:  # pycolmap raises plain RuntimeError/ValueError on bad files
        raise DataError(f"{sparse}: cannot read the COLMAP model ({err})") from None
    if len(rec.images) == 0:
        raise DataError(f"{sparse}: the model has no registered images")
    image_dir = root / images
    if not image_dir.is_dir():
        raise DataError(f"{image_dir}: image folder does not exist")
    entries = sorted(rec.images.values(), key=lambda im: im.name)
    paths = [image_dir / im.name for im in entries]
    for path in paths:
        if not path.exists():
            raise DataError(f"{path}: image of the COLMAP model is missing")
    file_w, file_h = image_size(paths[0])
    w = width or min(file_w, MAX_DEFAULT_WIDTH)
    h = round(file_h * w / file_w)
    viewmats, ks = [], []
    for im, path in zip(entries, paths):
        cam = rec.cameras[im.camera_id]
        fx, fy, cx, cy = _intrinsics(cam, sparse / "cameras", allow_distortion)
        if abs(cam.width / cam.height - file_w / file_h) > 0.01:
            raise DataError(f"{path}: aspect ratio {file_w}x{file_h} differs from the model's camera "
                            f"{cam.width}x{cam.height}")
        sx, sy = w / cam.width, h / cam.height
        ks.append([[fx * sx, 0, cx * sx], [0, fy * sy, cy * sy], [0, 0, 1]])
        pose = im.cam_from_world() if callable(im.cam_from_world) else im.cam_from_world
        m = torch.eye(4, dtype=torch.float64)
        m[:3] = torch.as_tensor(pose.matrix(), dtype=torch.float64)
        viewmats.append(m)
    cams = Cameras(torch.stack(viewmats).float(), torch.tensor(ks, dtype=torch.float32), w, h)
    bg = torch.tensor(background, dtype=torch.float32)
    names = [im.name for im in entries]
    store = ImageStore(paths, (w, h), bg, budget_mb, source_size=(file_w, file_h))
    test = [i for i in range(len(names)) if i % llff_hold == 0]
    train = [i for i in range(len(names)) if i % llff_hold != 0]
    splits = {"all": Split(cams, store, names),
              "train": Split(cams[train], store.subset(train), [names[i] for i in train]),
              "test": Split(cams[test], store.subset(test), [names[i] for i in test])}
    pts = list(rec.points3D.values())
    points = torch.from_numpy(np.array([p.xyz for p in pts], dtype=np.float32)) if pts else None
    colors = torch.from_numpy(np.array([p.color for p in pts], dtype=np.float32)) / 255 if pts else None
    return Scene(root.name, "colmap", root, splits, bg, points, colors,
                 info={"sparse": str(sparse), "model_size": [int(rec.cameras[entries[0].camera_id].width),
                                                             int(rec.cameras[entries[0].camera_id].height)]})


def observations(root: str | Path, image_name: str):
    """The 2D observations of one image and their 3D points: ([M, 2] pixels, [M, 3] points)."""
    import pycolmap

    rec = pycolmap.Reconstruction(str(_sparse_dir(Path(root))))
    im = next(i for i in rec.images.values() if i.name == image_name)
    pairs = [(p.xy, rec.points3D[p.point3D_id].xyz) for p in im.points2D if p.has_point3D()]
    xy = torch.tensor([list(a) for a, _ in pairs], dtype=torch.float64)
    xyz = torch.tensor([list(b) for _, b in pairs], dtype=torch.float64)
    return xy, xyz
