"""Does a structure-from-motion model hold together? Evenly spaced subsets of its photos,
reconstructed anew with exhaustive matching (the witnesses), aligned to the model's own cameras.

A small reprojection error does not prove a model: each neighbourhood of views can be explained
while the loop around the object is not closed, and the cameras of a 360-degree walk fold into an S
(`regressions/bonsai_folded`: 0.27 px, yet folded). Exhaustive matching of a subset closes every
loop the subset can see, so its cameras are a witness independent of how the model was matched.
After the similarity that best maps a witness's centres onto the model's (Umeyama,
``pipeline.data.alignment``; refitted without the cameras more than ``TRIM_FACTOR`` median errors off,
so a photo the witness registered wrongly does not bend the fit of the rest), the centre errors are
measured as a fraction of the cameras' diameter (the largest distance between two of the model's
centres), and each camera's rotation error as the median, over the other cameras, of the error of
their relative rotation (no alignment enters it, so a witness whose centres fit a little tilted is
not blamed for it). Above ``FOLD_CENTRE`` (median centre error) or ``FOLD_ROTATION_DEG`` (median
rotation error) the witness disagrees with the model.

A witness can itself be wrong. 59 of bonsai's small photos (399 x 266 px, 450-1,400 SIFT features
each) matched exhaustively with COLMAP's defaults gave, in 2 of 8 runs, a witness with a third of the
ring flipped (32 % median centre error against the sound model), and one more at 4.4 %, near the
threshold: false pairs between the two sides of a repetitive scene, 15 matches being the least that
links two photos. So a witness links two photos only on ``WITNESS_MIN_MATCHES`` verified matches
(measured, 4 runs: each agreed with the sound model, 0.4-0.6 % and 0.2-0.5 degrees, with 35-53 of the
59 photos in its largest piece), and up to ``WITNESSES`` witnesses are asked, each on other photos
(every ``step``-th from a different first) with its own random seed. The verdict: **consistent** as
soon as one witness that registered at least ``MIN_COVER`` of its subset agrees; **folded or
drifted** when every such witness disagrees; **inconclusive** when none registered that many. A
folded model is far from every sound witness (bonsai's folded model: 14-23 % of the diameter from each
of the 12 witnesses that agreed with the sound one, against the 5 % threshold), so asking more than
one costs time only on a model that fails.
"""

from __future__ import annotations

import math
import shutil
import tempfile
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Callable, Iterable, Iterator

import torch

from pipeline.cameras import Cameras
from pipeline.data.alignment import matched, pose_error_arrays, relative_rotation_errors
from pipeline.data.images import DataError

FOLD_CENTRE = 0.05        # median centre error over the cameras' diameter
FOLD_ROTATION_DEG = 3.0   # median rotation error, degrees
DEFAULT_EVERY = 5         # every 5th photo in name order
MAX_SUBSET = 80           # a subset above this takes a larger step (exhaustive pairs grow as n^2)
TRIM_FACTOR = 3.0         # the similarity is refitted without cameras this many medians off
TRIM_ROUNDS = 3
WITNESSES = 3             # subsets asked at most, each on other photos with its own seed
WITNESS_MIN_MATCHES = 50  # verified matches that link two photos in a witness (COLMAP's default: 15)
MIN_COVER = 0.5           # a witness that registered less of its subset is not asked
CONSISTENT, FOLDED, INCONCLUSIVE = "consistent", "folded or drifted", "inconclusive"

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
    subset: int                        # photos reconstructed anew (of the witness quoted)
    every: int                         # the step through the model's images in name order
    registered: int                    # of the subset, in the witness's largest model (matched by name)
    median_centre_error: float | None  # over the cameras' diameter (None: inconclusive)
    max_centre_error: float | None
    median_rotation_error_deg: float | None  # of the cameras' relative rotations (see the module's text)
    max_rotation_error_deg: float | None
    verdict: str                       # consistent | folded or drifted | inconclusive
    fitted_on: int = 0                 # cameras the similarity was fitted on (the rest: > 3 medians off)
    first: int = 0                     # the witness's first photo (it takes every ``every``-th from it)
    witnesses: list[dict] = field(default_factory=list)  # every witness asked, in order: its figures
    thresholds: dict = field(default_factory=lambda: {"median_centre_error": FOLD_CENTRE,
                                                      "median_rotation_error_deg": FOLD_ROTATION_DEG})
    seconds: float = 0.0

    @property
    def folded(self) -> bool:
        return self.verdict == FOLDED

    def figures(self) -> dict:
        """One witness's figures, as ``witnesses`` lists them."""
        return {k: getattr(self, k) for k in ("first", "subset", "registered", "fitted_on", "median_centre_error",
                                              "max_centre_error", "median_rotation_error_deg",
                                              "max_rotation_error_deg", "verdict")}

    def line(self) -> str:
        if self.median_centre_error is None or self.max_centre_error is None:
            return (f"geometry check: inconclusive: no witness registered {100 * MIN_COVER:.0f}% of its photos (at most "
                    f"{self.registered} of {self.subset}, every {self.every}th; {len(self.witnesses)} asked)")
        asked = (f" ({len(self.witnesses)} witnesses asked, this the "
                 f"{'one that agrees' if self.verdict == CONSISTENT else 'closest'})" if len(self.witnesses) > 1 else "")
        return (f"geometry check: {self.registered} of {self.subset} photos (every {self.every}th from photo "
                f"{self.first + 1}) reconstructed anew with exhaustive matching{asked}: median centre error "
                f"{100 * self.median_centre_error:.1f}% of the cameras' diameter (max {100 * self.max_centre_error:.1f}%), "
                f"relative rotation {self.median_rotation_error_deg:.2f} deg (max {self.max_rotation_error_deg:.2f}; "
                f"aligned on {self.fitted_on} of them, the others more than {TRIM_FACTOR:.0f} medians off): {self.verdict}")

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


def reconstruct_subset(model: ModelPoses, every: int, work: Path, say: Progress, first: int = 0,
                       seed: int | None = None) -> tuple[ModelPoses, int]:
    """Every ``every``-th image (name order) from the ``first``-th, reconstructed with exhaustive
    matching in ``work`` (two photos linked on ``WITNESS_MIN_MATCHES`` matches, COLMAP seeded with
    ``seed``); the new model's poses (largest model) and the subset's size."""
    from pipeline.data.sfm import CaptureError, reconstruct  # pycolmap: imported when a check runs
    chosen = list(range(first, len(model.names), every))
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
    try:
        rec, _ = reconstruct(work, names, "exhaustive", say, {}, min_num_matches=WITNESS_MIN_MATCHES, seed=seed)
    except CaptureError:  # no model at all: a witness with nothing registered
        return ModelPoses([], torch.zeros(0, 4, 4, dtype=torch.float64), []), len(names)
    registered, viewmats = image_poses(rec.image(i) for i in rec.reg_image_ids())
    return ModelPoses(registered, viewmats, []), len(names)


def image_key(name: str) -> str:
    """A photo's name without its folder separators and extension (the two models name them alike)."""
    return name.replace("/", "_").rsplit(".", 1)[0]


def compare(model: ModelPoses, subset: ModelPoses, subset_size: int, every: int, seconds: float = 0.0,
            first: int = 0) -> GeometryCheck:
    """One witness's cameras against the model's (matched by file name), after a similarity; a
    witness that registered less than ``MIN_COVER`` of its subset gives the verdict inconclusive."""
    if len(subset.names) < max(3, MIN_COVER * subset_size):
        return GeometryCheck(len(model.names), subset_size, every, len(subset.names), None, None, None, None,
                             INCONCLUSIVE, first=first, seconds=round(seconds, 1))
    true, est, _ = matched(model.names, model.cameras(), subset.names, subset.cameras(), key=image_key)
    errors, centre, _ = pose_error_arrays(true, est)
    fit_on = list(range(len(true)))
    for _ in range(TRIM_ROUNDS):  # a camera the subset registered wrongly must not bend the fit of the rest
        keep = [i for i in range(len(true)) if centre[i] <= TRIM_FACTOR * float(centre[fit_on].median())]
        if len(keep) < 3 or keep == fit_on:
            break
        fit_on = keep
        errors, centre, _ = pose_error_arrays(true, est, fit_on)
    rotation = relative_rotation_errors(true, est)
    centres = true.centers.double()
    diameter = float(torch.cdist(centres, centres).max())
    scale = errors.scene_extent / diameter  # pose_errors measures against the largest radius
    median, largest = errors.median_centre_error * scale, errors.max_centre_error * scale
    median_rotation = float(rotation.median())
    folded = median > FOLD_CENTRE or median_rotation > FOLD_ROTATION_DEG
    return GeometryCheck(len(model.names), subset_size, every, len(true), round(median, 5), round(largest, 5),
                         round(median_rotation, 3), round(float(rotation.max()), 3), FOLDED if folded else CONSISTENT,
                         fitted_on=len(fit_on), first=first, seconds=round(seconds, 1))


def witness_firsts(every: int, count: int = WITNESSES) -> list[int]:
    """The first photo of each witness: 0, 1, 2, ... (wrapping past ``every``: then only the seed differs)."""
    return [k % every for k in range(count)]


def witnesses(model: ModelPoses, every: int, work: Path, say: Progress, count: int = WITNESSES
              ) -> Iterator[tuple[int, ModelPoses, int]]:
    """The witnesses of ``model``, made one at a time as they are asked for (witness k: every
    ``every``-th photo from ``witness_firsts``' k-th, COLMAP seeded with k, in ``work/witness_k``)."""
    for k, first in enumerate(witness_firsts(every, count)):
        say(f"geometry check: witness {k + 1} (every {every}th photo from photo {first + 1}) ...")
        subset, size = reconstruct_subset(model, every, work / f"witness_{k}", say, first=first, seed=k)
        yield first, subset, size


def verdict(model: ModelPoses, witnesses: Iterable[tuple[int, ModelPoses, int]], every: int,
            seconds: Callable[[], float] = lambda: 0.0) -> GeometryCheck:
    """The model against witnesses (first photo, cameras, subset size) taken in order, stopping at
    the first that agrees (see the module's text for the verdict)."""
    asked: list[GeometryCheck] = []
    for first, subset, size in witnesses:
        asked.append(compare(model, subset, size, every, first=first))
        if asked[-1].verdict == CONSISTENT:
            break
    if not asked:
        raise ValueError("geometry check: no witness to ask")
    heard = [c for c in asked if c.verdict != INCONCLUSIVE]
    quoted = asked[-1] if asked[-1].verdict == CONSISTENT else (
        min(heard, key=lambda c: c.median_centre_error or 0.0) if heard else max(asked, key=lambda c: c.registered))
    return replace(quoted, witnesses=[c.figures() for c in asked], seconds=round(seconds(), 1))


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
    folder = Path(tempfile.mkdtemp(prefix="gopre-geometry-")) if work is None else work
    try:
        return verdict(model, witnesses(model, step, folder, say), step, lambda: time.perf_counter() - start)
    finally:
        if work is None:
            shutil.rmtree(folder, ignore_errors=True)
