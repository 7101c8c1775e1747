"""Does a structure-from-motion model hold together? An evenly spaced subset of its photos,
reconstructed anew with exhaustive matching, aligned to the model's own cameras.

A small reprojection error does not prove a model: each neighbourhood of views can be explained
while the loop around the object is not closed, and the cameras of a 360-degree walk fold into an S
(`regressions/bonsai_folded`: 0.27 px, yet folded). Exhaustive matching of a subset closes every
loop the subset can see, so its cameras are a witness independent of how the model was matched.
After the similarity that best maps the subset's centres onto the model's (Umeyama,
``pipeline.data.alignment``; refitted without the cameras more than ``TRIM_FACTOR`` median errors off,
so a photo the subset registered wrongly does not bend the fit of the rest), the centre errors are measured as a fraction of the cameras'
diameter (the largest distance between two of the model's centres) and the rotation errors in
degrees. Above ``FOLD_CENTRE`` (median centre error) or ``FOLD_ROTATION_DEG`` (median rotation
error) the model is called folded or drifted.

Measured: the folded bonsai model's median centre error is about a third of the ring's size and its
rotations are several degrees off; a sound model agrees to about 1 %.
"""

from __future__ import annotations

import math
import shutil
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import torch

from pipeline.cameras import Cameras
from pipeline.data.alignment import matched, pose_error_arrays
from pipeline.data.images import DataError

FOLD_CENTRE = 0.05        # median centre error over the cameras' diameter
FOLD_ROTATION_DEG = 3.0   # median rotation error, degrees
DEFAULT_EVERY = 5         # every 5th photo in name order
MAX_SUBSET = 80           # a subset above this takes a larger step (exhaustive pairs grow as n^2)
TRIM_FACTOR = 3.0         # the similarity is refitted without cameras this many medians off
TRIM_ROUNDS = 3

Progress = Callable[[str], None]


@dataclass
class ModelPoses:
    """A model's registered images: names, world->camera [C, 4, 4] float64, the image files."""

    names: list[str]
    viewmats: torch.Tensor
    images: list[Path]

    def cameras(self) -> Cameras:
        ks = torch.eye(3, dtype=torch.float32).expand(len(self.names), 3, 3).clone()  # poses only
        return Cameras(self.viewmats.float(), ks, 1, 1)


@dataclass
class GeometryCheck:
    """The figures of one check, as ``capture.json`` and ``gopre-data geometry`` keep them."""

    model_images: int
    subset: int                        # photos reconstructed anew
    every: int                         # the step through the model's images in name order
    registered: int                    # of the subset, in the new model (and matched by name)
    median_centre_error: float         # over the cameras' diameter
    max_centre_error: float
    median_rotation_error_deg: float
    max_rotation_error_deg: float
    verdict: str                       # consistent | folded or drifted
    fitted_on: int = 0                 # cameras the similarity was fitted on (the rest: > 3 medians off)
    thresholds: dict = field(default_factory=lambda: {"median_centre_error": FOLD_CENTRE,
                                                      "median_rotation_error_deg": FOLD_ROTATION_DEG})
    seconds: float = 0.0

    @property
    def folded(self) -> bool:
        return self.verdict != "consistent"

    def line(self) -> str:
        return (f"geometry check: {self.registered} of {self.subset} photos (every {self.every}th) reconstructed anew "
                f"with exhaustive matching: median centre error {100 * self.median_centre_error:.1f}% of the cameras' "
                f"diameter (max {100 * self.max_centre_error:.1f}%), rotation {self.median_rotation_error_deg:.2f} deg "
                f"(max {self.max_rotation_error_deg:.2f}; aligned on {self.fitted_on} of them, the others more than "
                f"{TRIM_FACTOR:.0f} medians off): {self.verdict}")

    def to_dict(self) -> dict:
        return asdict(self)


def colmap_poses(root: Path, images: Path | None = None) -> ModelPoses:
    """The registered images of the COLMAP model in ``root`` (``sparse/0`` or ``sparse``, or ``root``
    itself when it holds the model files), images from ``images`` (default ``root/images``)."""
    import pycolmap

    from pipeline.data.colmap import sparse_dir
    sparse = root if (root / "cameras.bin").exists() or (root / "cameras.txt").exists() else sparse_dir(root)
    try:
        rec = pycolmap.Reconstruction(str(sparse))
    except Exception as err:
        raise DataError(f"{sparse}: cannot read the COLMAP model ({err})") from None
    names, viewmats = image_poses(rec.images.values())
    folder = images or root / "images"
    return ModelPoses(names, viewmats, [folder / name for name in names])


def image_poses(images) -> tuple[list[str], torch.Tensor]:
    """pycolmap images in name order: their names and world->camera [C, 4, 4] float64."""
    entries = sorted(images, key=lambda im: im.name)
    viewmats = torch.eye(4, dtype=torch.float64).repeat(len(entries), 1, 1)
    for k, im in enumerate(entries):
        pose = im.cam_from_world() if callable(im.cam_from_world) else im.cam_from_world
        viewmats[k, :3] = torch.as_tensor(pose.matrix(), dtype=torch.float64)
    return [im.name for im in entries], viewmats


def nerfstudio_poses(root: Path, images: Path | None = None) -> ModelPoses:
    from pipeline.data.nerfstudio import frame_viewmats, load_transforms
    meta = load_transforms(root)
    frames = sorted(meta["frames"], key=lambda f: str(f["file_path"]))
    base = images or root
    files = [(base / Path(f["file_path"]).name) if images else (root / f["file_path"]) for f in frames]
    return ModelPoses([Path(f["file_path"]).name for f in frames], frame_viewmats(frames, root / "transforms.json"),
                      files)


def model_poses(path: str | Path, images: str | Path | None = None) -> ModelPoses:
    """A COLMAP or nerfstudio scene's poses (a bare COLMAP model folder too, with ``images``)."""
    path, images = Path(path), Path(images) if images else None
    if (path / "transforms.json").exists():
        return nerfstudio_poses(path, images)
    return colmap_poses(path, images)


def subset_step(count: int, every: int) -> int:
    """The step through ``count`` images: ``every``, larger when that would exceed ``MAX_SUBSET``."""
    return max(every, math.ceil(count / MAX_SUBSET))


def reconstruct_subset(model: ModelPoses, every: int, work: Path, say: Progress) -> tuple[ModelPoses, int]:
    """Every ``every``-th image (name order) reconstructed with exhaustive matching in ``work``;
    the new model's poses (largest model) and the subset's size."""
    from pipeline.data.sfm import reconstruct  # pycolmap: imported when a check runs
    chosen = list(range(0, len(model.names), every))
    missing = [str(model.images[i]) for i in chosen if not model.images[i].is_file()]
    if missing:
        raise DataError(f"{missing[0]}: an image of the model is missing ({len(missing)} missing; --images DIR "
                        "names the folder that holds them)")
    (work / "images").mkdir(parents=True)
    names = []
    for i in chosen:
        name = model.names[i].replace("/", "_")
        shutil.copy(model.images[i], work / "images" / name)
        names.append(name)
    rec, _ = reconstruct(work, names, "exhaustive", say, {})
    registered, viewmats = image_poses(rec.image(i) for i in rec.reg_image_ids())
    if len(registered) < 3:
        raise DataError(f"geometry check: only {len(registered)} of {len(names)} subset photos registered; "
                        "nothing to align")
    return ModelPoses(registered, viewmats, []), len(names)


def image_key(name: str) -> str:
    """A photo's name without its folder separators and extension (the two models name them alike)."""
    return name.replace("/", "_").rsplit(".", 1)[0]


def compare(model: ModelPoses, subset: ModelPoses, subset_size: int, every: int, seconds: float = 0.0) -> GeometryCheck:
    """The subset's cameras against the model's (matched by file name), after a similarity."""
    true, est, _ = matched(model.names, model.cameras(), subset.names, subset.cameras(), key=image_key)
    errors, centre, _ = pose_error_arrays(true, est)
    fit_on = list(range(len(true)))
    for _ in range(TRIM_ROUNDS):  # a camera the subset registered wrongly must not bend the fit of the rest
        keep = [i for i in range(len(true)) if centre[i] <= TRIM_FACTOR * float(centre[fit_on].median())]
        if len(keep) < 3 or keep == fit_on:
            break
        fit_on = keep
        errors, centre, _ = pose_error_arrays(true, est, fit_on)
    centres = true.centers.double()
    diameter = float(torch.cdist(centres, centres).max())
    scale = errors.scene_extent / diameter  # pose_errors measures against the largest radius
    median, largest = errors.median_centre_error * scale, errors.max_centre_error * scale
    folded = median > FOLD_CENTRE or errors.median_rotation_error_deg > FOLD_ROTATION_DEG
    return GeometryCheck(len(model.names), subset_size, every, len(true), round(median, 5), round(largest, 5),
                         round(errors.median_rotation_error_deg, 3), round(errors.max_rotation_error_deg, 3),
                         "folded or drifted" if folded else "consistent", fitted_on=len(fit_on),
                         seconds=round(seconds, 1))


def check_geometry(path: str | Path, images: str | Path | None = None, every: int = DEFAULT_EVERY,
                   say: Progress | None = None, work: Path | None = None) -> GeometryCheck:
    """The geometry check of the scene (or model) in ``path`` (see the module's text)."""
    if every < 2:
        raise ValueError(f"every must be at least 2 (every photo would be a full exhaustive reconstruction), got {every}")
    say = say or (lambda line: None)
    start = time.perf_counter()
    model = model_poses(path, images)
    step = subset_step(len(model.names), every)
    if len(range(0, len(model.names), step)) < 3:
        raise DataError(f"{path}: {len(model.names)} registered images; a geometry check needs at least 3 in its "
                        f"subset (every {step}th)")
    own = work is None
    work = Path(tempfile.mkdtemp(prefix="gopre-geometry-")) if own else work
    try:
        subset, size = reconstruct_subset(model, step, work, say)
    finally:
        if own:
            shutil.rmtree(work, ignore_errors=True)
    return compare(model, subset, size, step, time.perf_counter() - start)
