"""COLMAP reader (Mip-NeRF360, Tanks & Temples): a sparse model read with pycolmap, binary or text.

Cameras: PINHOLE, SIMPLE_PINHOLE, SIMPLE_RADIAL, RADIAL and OPENCV. A model with non-zero lens
distortion is undistorted on load (COLMAP's image undistorter, to PINHOLE) into a cache folder
(``GOPRE_CACHE``, default ``~/.cache/gopre/undistorted/<scene>-<hash of the model and images>``),
never into the user's folder, and read from there; ``allow_distortion=True`` reads the distorted
images as they are, ignoring the distortion (a test's shortcut, not a result). The image folder may hold any resolution (images_N,
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

SUPPORTED = {"PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV"}


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


def sparse_dir(root: Path) -> Path:
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
    elif model in ("SIMPLE_RADIAL", "RADIAL"):  # f, cx, cy, k1 (, k2)
        fx, fy, cx, cy, dist = p[0], p[0], p[1], p[2], p[3:]
    else:  # OPENCV: fx, fy, cx, cy, k1, k2, p1, p2
        fx, fy, cx, cy, dist = p[0], p[1], p[2], p[3], p[4:]
    if any(abs(d) > 0 for d in dist) and not allow_distortion:
        raise DataError(f"{path}: camera {cam.camera_id} ({model}) has non-zero distortion {dist} "
                        "(read_colmap undistorts such a model first)")
    return fx, fy, cx, cy


def distorted(rec) -> bool:
    """Whether any camera of the model has non-zero distortion parameters."""
    for cam in rec.cameras.values():
        model = cam.model.name if hasattr(cam.model, "name") else str(cam.model)
        extra = {"SIMPLE_RADIAL": 3, "RADIAL": 3, "OPENCV": 4}.get(model)
        if extra is not None and any(abs(float(x)) > 0 for x in list(cam.params)[extra:]):
            return True
    return False


def cache_root() -> Path:
    import os
    return Path(os.environ.get("GOPRE_CACHE", Path.home() / ".cache" / "gopre")) / "undistorted"


def undistorted_copy(root: Path, sparse: Path, image_dir: Path, masks_dir: Path | None) -> Path:
    """The scene undistorted to PINHOLE in the cache (made once; keyed by the model's files and
    the images' names, sizes and times): ``<cache>/images``, ``<cache>/sparse/0``, ``<cache>/masks``."""
    import hashlib
    import os
    import shutil

    import pycolmap
    digest = hashlib.sha256()
    for path in sorted(sparse.iterdir()):
        digest.update(path.name.encode() + path.read_bytes())
    for folder in (image_dir, masks_dir):
        for path in sorted(folder.iterdir()) if folder is not None else []:
            st = path.stat()
            digest.update(f"{folder.name}/{path.name}:{st.st_size}:{st.st_mtime_ns}".encode())
    target = cache_root() / f"{root.name}-{digest.hexdigest()[:16]}"
    if (target / "sparse" / "0" / "cameras.bin").exists():
        return target
    staging = target.with_name(f"{target.name}.tmp-{os.getpid()}")
    shutil.rmtree(staging, ignore_errors=True)
    try:
        staging.mkdir(parents=True)
        pycolmap.undistort_images(staging / "u", sparse, image_dir)
        (staging / "sparse").mkdir(parents=True)
        shutil.move(str(staging / "u" / "sparse"), str(staging / "sparse" / "0"))
        shutil.move(str(staging / "u" / "images"), str(staging / "images"))
        if masks_dir is not None:
            undistort_masks(sparse, image_dir, masks_dir, staging)
        shutil.rmtree(staging / "u", ignore_errors=True)
        target.parent.mkdir(parents=True, exist_ok=True)
        os.replace(staging, target)
    except (OSError, RuntimeError) as err:  # pycolmap reports a file system error as RuntimeError
        raise DataError(f"{root}: cannot write the undistorted copy under {cache_root()} ({err}); "
                        "set GOPRE_CACHE to a writable folder") from None
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return target


def undistort_masks(sparse: Path, image_dir: Path, masks_dir: Path, staging: Path) -> None:
    """Each image's mask through the same undistortion (nearest pixel kept at >= 0.5) into
    ``staging/masks/<stem>.png``."""
    import pycolmap
    from PIL import Image
    rgb = staging / "mask_rgb"
    rgb.mkdir(parents=True)
    for image in sorted(image_dir.iterdir()):
        mask = mask_path(masks_dir, image.name)
        if mask is not None:
            with Image.open(mask) as im:
                im.convert("RGB").save(rgb / image.name)
    pycolmap.undistort_images(staging / "m", sparse, rgb)
    (staging / "masks").mkdir()
    for path in sorted((staging / "m" / "images").iterdir()):
        with Image.open(path) as im:
            values = np.asarray(im.convert("L"))
        Image.fromarray(((values >= 128) * 255).astype(np.uint8)).save(staging / "masks" / f"{Path(path.name).stem}.png")


def mask_path(masks_dir: Path, image_name: str) -> Path | None:
    """An image's mask: ``<stem>.png``, the image's own name, or ``<stem>_mask.png``."""
    stem = Path(image_name).stem
    for name in (f"{stem}.png", image_name, f"{stem}_mask.png"):
        if (masks_dir / name).is_file():
            return masks_dir / name
    return None


def scene_masks(root: Path, masks_dir: Path, names: list[str], splits: dict[str, list[int]]) -> dict[str, list[Path]]:
    """Per split the mask file of each image; a folder without masks, or an image without one,
    is an error naming them."""
    if not masks_dir.is_dir():
        raise DataError(f"{root}: masks were asked for (data masks=true) but {masks_dir} does not exist")
    paths = [mask_path(masks_dir, n) for n in names]
    missing = [n for n, p in zip(names, paths) if p is None]
    if missing:
        raise DataError(f"{masks_dir}: no mask for {len(missing)} image(s): {', '.join(missing[:10])}")
    return {split: [paths[i] for i in ids] for split, ids in splits.items()}


# 3DGS's resolution rule: without an explicit width, images wider than 1600 px train at 1600 px.
MAX_DEFAULT_WIDTH = 1600


def read_colmap(root: str | Path, width: int | None = None, images: str = "images",
                background=(0.0, 0.0, 0.0), llff_hold: int = 8, allow_distortion: bool = False,
                budget_mb: float = 1024.0, masks: bool = False) -> Scene:
    """Read a COLMAP scene; images resized to ``width`` (None = as stored in ``images``, but at
    most ``MAX_DEFAULT_WIDTH`` px wide, 3DGS's rule).

    Splits: ``train`` and ``test`` by the LLFF hold-out (every ``llff_hold``-th image in name
    order is a test view), and ``all`` in name order. ``masks``: each image's mask from
    ``root/masks`` (``<stem>.png``, the image's name or ``<stem>_mask.png``).
    """
    import pycolmap

    root = Path(root)
    if not root.is_dir():
        raise DataError(f"{root}: scene folder does not exist")
    sparse = sparse_dir(root)
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
    if distorted(rec) and not allow_distortion:  # read the undistorted copy instead (cached)
        copy = undistorted_copy(root, sparse, image_dir, root / "masks" if masks else None)
        scene = read_colmap(copy, width, "images", background, llff_hold, False, budget_mb, masks)
        scene.name, scene.root = root.name, root
        scene.info["undistorted"] = str(copy)
        chosen = capture_up(root)
        if chosen is not None:
            scene.info["up"] = chosen
        return scene
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
    mask_files = (scene_masks(root, root / "masks", names, {"all": list(range(len(names))), "train": train,
                                                            "test": test}) if masks else None)
    info = {"sparse": str(sparse), "model_size": [int(rec.cameras[entries[0].camera_id].width),
                                                  int(rec.cameras[entries[0].camera_id].height)]}
    chosen = capture_up(root)
    if chosen is not None:  # gopre-data capture --up: the scene's own up axis
        info["up"] = chosen
    return Scene(root.name, "colmap", root, splits, bg, points, colors, info=info, masks=mask_files)


def capture_up(root: Path) -> str | list | None:
    """The up axis ``gopre-data capture --up`` chose for the scene (``capture.json``'s
    ``orientation.choice``), None when it chose none."""
    import json
    path = root / "capture.json"
    if not path.exists():
        return None
    try:
        choice = (json.loads(path.read_text()).get("orientation") or {}).get("choice")
    except (OSError, ValueError, AttributeError) as err:
        raise DataError(f"{path}: cannot read it ({err})") from None
    if choice is None:
        return None
    from pipeline.data.orientation import parse_up
    try:
        return parse_up(choice)
    except ValueError as err:
        raise DataError(f"{path}: orientation.choice: {err}") from None


def observed_points(root: str | Path, image_names: list[str]) -> list["torch.Tensor"]:
    """The world points [M, 3] (float64) each named image observed (its track's 3D points), the
    model read once; an image the model does not have gets an empty set."""
    import pycolmap

    rec = pycolmap.Reconstruction(str(sparse_dir(Path(root))))
    by_name = {im.name: im for im in rec.images.values()}
    out = []
    for name in image_names:
        im = by_name.get(name)
        xyz = [list(rec.points3D[p.point3D_id].xyz) for p in im.points2D if p.has_point3D()] if im else []
        out.append(torch.tensor(xyz, dtype=torch.float64).reshape(-1, 3))
    return out


def observations(root: str | Path, image_name: str):
    """The 2D observations of one image and their 3D points: ([M, 2] pixels, [M, 3] points)."""
    import pycolmap

    rec = pycolmap.Reconstruction(str(sparse_dir(Path(root))))
    im = next(i for i in rec.images.values() if i.name == image_name)
    pairs = [(p.xy, rec.points3D[p.point3D_id].xyz) for p in im.points2D if p.has_point3D()]
    xy = torch.tensor([list(a) for a, _ in pairs], dtype=torch.float64)
    xyz = torch.tensor([list(b) for _, b in pairs], dtype=torch.float64)
    return xy, xyz
