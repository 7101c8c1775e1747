"""Photos (or a video) in, a COLMAP scene out: structure-from-motion with pycolmap on the CPU.

    capture_scene(PHOTOS_DIR | VIDEO, OUT)

1. the inputs: every image of the folder (unreadable files named before any work), or sharp
   frames chosen evenly from a video (``video.sharp_frames``); copies resized to at most
   ``max_size`` px (the user's files are never written);
2. SIFT features (one shared SIMPLE_RADIAL camera), matching, incremental mapping; the largest
   model is kept and the others are listed; fewer than half of the images registered is an error
   naming the ones that did not. Matching: exhaustive up to ``EXHAUSTIVE_UP_TO`` photos; above it
   each photo with its ``NEIGHBOURS`` next in name (walk) order plus every pair among an evenly
   spaced skeleton (every ``SKELETON_EVERY``-th photo), which closes the loop of a walk around the
   object without a vocabulary tree (``loop_pairs``); sequential for video frames. A line of
   progress during features and matching (``LogProgress``, from COLMAP's own log);
   a model not matched exhaustively then gets the geometry check (``geometry_check``: an evenly
   spaced subset reconstructed with exhaustive matching and aligned to it), which says when the
   model is folded or drifted; a loop-matched model that fails it is matched again exhaustively and
   mapped anew (the first attempt kept in ``capture.json``'s ``first_try``);
3. the kept model undistorted to a PINHOLE camera (COLMAP's image undistorter) into
   ``OUT/images`` + ``OUT/sparse/0``; masks that come with the photos (``masks/`` beside them, named
   like the photo, ``<stem>.png`` or ``<stem>_mask.png``: ``colmap.mask_path``) are undistorted the
   same way into ``OUT/masks``;
4. ``OUT/capture.json``: images, registered, points, mean reprojection error, seconds per stage,
   the photos that did not register, the sizes of the models that were left out, the matching's
   pairs and the geometry check's figures.
"""

from __future__ import annotations

import json
import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

from PIL import Image, UnidentifiedImageError

from pipeline.data.colmap import mask_path, undistort_masks
from pipeline.data.sfm import (NEIGHBOURS, PROGRESS_SECONDS, SKELETON_EVERY, CaptureError,  # noqa: F401 (public here too)
                               LogProgress, loop_pairs, pair_count, quiet_colmap, reconstruct)

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")
VIDEO_SUFFIXES = (".mp4", ".mov", ".avi", ".mkv", ".webm", ".m4v")
MIN_IMAGES = 8               # fewer cannot cover an object well enough to pick views from
EXHAUSTIVE_UP_TO = 200       # photo sets above this are matched along the walk plus a skeleton (pairs grow as n^2)


@dataclass
class CaptureSummary:
    source: str
    out: str
    images: int
    registered: int
    points: int
    mean_reprojection_error_px: float
    camera_model: str
    matcher: str
    seconds: dict[str, float] = field(default_factory=dict)
    unregistered: list[str] = field(default_factory=list)
    other_models: list[int] = field(default_factory=list)   # registered images of each model left out
    masks: int = 0
    pairs: int | None = None        # image pairs matched (None: sequential video matching)
    geometry: dict | None = None    # the geometry check's figures (None: matched exhaustively)
    orientation: dict | None = None  # the up axis: the choice (--up), every estimate, their angles
    first_try: dict | None = None   # a loop-matched attempt that failed the geometry check (then matched exhaustively)

    def to_dict(self) -> dict:
        return asdict(self)


Progress = Callable[[str], None]


def photo_files(folder: Path) -> list[Path]:
    """The images of a photo folder in name order; unreadable ones are an error naming each."""
    files = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
    bad = []
    for path in files:  # decoded whole: verify() passes a truncated JPEG, which SIFT then fails on
        try:
            with Image.open(path) as im:
                im.load()
        except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as err:
            bad.append(f"{path.name} ({err})")
    if bad:
        raise CaptureError(f"{folder}: {len(bad)} unreadable image file(s): {', '.join(bad[:10])}"
                           + (" ..." if len(bad) > 10 else ""))
    return files


def resized_copy(src: Path, dst: Path, max_size: int, mode: str = "RGB") -> None:
    with Image.open(src) as im:
        im = im.convert(mode)
        scale = max_size / max(im.size)
        if scale < 1:
            im = im.resize((round(im.width * scale), round(im.height * scale)),
                           Image.LANCZOS if mode == "RGB" else Image.NEAREST)
        im.save(dst, quality=95) if dst.suffix.lower() in (".jpg", ".jpeg") else im.save(dst)


def prepare_inputs(source: Path, work: Path, max_size: int, frames: int, say: Progress) -> tuple[list[str], str, int]:
    """Copies of the inputs in ``work/images`` (and ``work/masks``); returns the image names, the
    matcher (exhaustive | sequential) and the number of masks."""
    images_dir, masks_dir = work / "images", work / "masks"
    images_dir.mkdir(parents=True)
    if source.is_file():
        if source.suffix.lower() not in VIDEO_SUFFIXES:
            raise CaptureError(f"{source}: not a photo folder or a video ({', '.join(VIDEO_SUFFIXES)})")
        from pipeline.data.video import sharp_frames
        chosen = sharp_frames(source, frames, say)
        names = []
        for k, frame in enumerate(chosen):
            name = f"frame_{k:05d}.jpg"
            Image.fromarray(frame).save(images_dir / name, quality=95)
            resized_copy(images_dir / name, images_dir / name, max_size)
            names.append(name)
        return names, "sequential", 0
    if not source.is_dir():
        raise CaptureError(f"{source}: no such folder or video file")
    photos = photo_files(source)
    if len(photos) < MIN_IMAGES:
        raise CaptureError(f"{source}: {len(photos)} image(s); a capture needs at least {MIN_IMAGES} photos "
                           "taken all around the object")
    masks_src = source.parent / "masks" if (source.parent / "masks").is_dir() else source / "masks"
    count = 0
    for k, photo in enumerate(photos):
        resized_copy(photo, images_dir / photo.name, max_size)
        mask = mask_path(masks_src, photo.name) if masks_src.is_dir() else None
        if mask is not None:  # lossless, under the name undistort_masks looks for
            masks_dir.mkdir(exist_ok=True)
            resized_copy(mask, masks_dir / f"{photo.stem}.png", max_size, mode="L")
            count += 1
        if (k + 1) % max(1, len(photos) // 4) == 0 or k + 1 == len(photos):
            say(f"inputs: {k + 1}/{len(photos)} photos copied (at most {max_size} px)")
    if 0 < count < len(photos):
        raise CaptureError(f"{masks_src}: masks for {count} of {len(photos)} photos; give one per photo or none")
    return [p.name for p in photos], "exhaustive" if len(photos) <= EXHAUSTIVE_UP_TO else "loop", count


def undistort(work: Path, model_dir: Path, out: Path, has_masks: bool) -> None:
    """The kept model and its images undistorted to PINHOLE in ``out`` (images/, sparse/0/);
    masks through the same cameras into ``out/masks`` (``colmap.undistort_masks``)."""
    import pycolmap
    staging = work / "undistorted"
    pycolmap.undistort_images(staging, model_dir, work / "images")
    (out / "sparse").mkdir(parents=True, exist_ok=True)
    shutil.copytree(staging / "sparse", out / "sparse" / "0", dirs_exist_ok=True)
    shutil.copytree(staging / "images", out / "images", dirs_exist_ok=True)
    if has_masks:
        undistort_masks(model_dir, work / "images", work / "masks", work / "mask_undistortion")
        shutil.copytree(work / "mask_undistortion" / "masks", out / "masks", dirs_exist_ok=True)


def orient(out: Path, up: str | list | None, say: Progress) -> dict:
    """The scene's up axis as ``capture.json`` keeps it (``choice``: what ``--up`` asked for, which
    the reader then uses; None: the cameras', as for any COLMAP scene), every estimate, and the
    line that warns when they disagree."""
    import pycolmap
    import torch

    from pipeline.data.geometry_check import colmap_poses
    from pipeline.data.orientation import orientation
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    points = torch.tensor([list(p.xyz) for p in rec.points3D.values()], dtype=torch.float64) if rec.num_points3D() else None
    found = orientation(colmap_poses(out).cameras(), points, up)
    say(f"up axis: {found.method} {[round(x, 3) for x in found.up]}; the other estimates "
        + ", ".join(f"{m} {a:.0f} deg away" for m, a in found.angles_deg.items() if m != found.method))
    if found.warning():
        say(f"warning: {found.warning()}")
    return {"choice": up, **found.to_dict()}


MATCHERS = ("auto", "exhaustive", "loop", "sequential")


@dataclass
class Mapped:
    """One structure-from-motion attempt: the kept model, the others' sizes, what registered."""

    model: object
    others: list[int]
    registered: set[str]
    missing: list[str]
    geometry: dict | None = None


def map_once(source: Path, work: Path, out: Path, names: list[str], matcher: str, masks: int, say: Progress,
             seconds: dict) -> Mapped:
    """Features, matching and mapping in ``work``, the kept model undistorted into ``out``, and, for
    a model not matched exhaustively, the geometry check (``Mapped.geometry``)."""
    model, others = reconstruct(work, names, matcher, say, seconds)
    registered = {model.image(i).name for i in model.reg_image_ids()}
    missing = [n for n in names if n not in registered]
    if len(registered) * 2 < len(names):
        raise CaptureError(f"{source}: only {len(registered)} of {len(names)} images registered in the largest "
                           f"model (others: {others or 'none'}); not registered: {', '.join(missing[:20])}"
                           + (" ..." if len(missing) > 20 else ""))
    model_dir = work / "kept"
    model_dir.mkdir()
    model.write(model_dir)
    t = time.perf_counter()
    say(f"undistorting {len(registered)} images{' and masks' if masks else ''} to PINHOLE ...")
    undistort(work, model_dir, out, masks > 0)
    seconds["undistortion"] = round(time.perf_counter() - t, 1)
    mapped = Mapped(model, others, registered, missing)
    if matcher != "exhaustive":  # a model matched along the walk may be folded: check it
        from pipeline.data.geometry_check import check_geometry
        t = time.perf_counter()
        say("geometry check: an evenly spaced subset reconstructed with exhaustive matching ...")
        check = check_geometry(out, say=say, work=work / "geometry")
        seconds["geometry_check"] = round(time.perf_counter() - t, 1)
        say(("warning: the model is FOLDED OR DRIFTED: " if check.folded else "") + check.line())
        mapped.geometry = check.to_dict()
    return mapped


def retry_exhaustive(work: Path, out: Path) -> Path:
    """Make room for a second, exhaustive attempt: the first attempt's database, models and
    undistorted output moved aside (into ``work/loop_attempt``); the copied inputs stay."""
    aside = work / "loop_attempt"
    aside.mkdir()
    for name in ("database.db", "sparse", "kept", "undistorted", "geometry", "pairs.txt", "mask_undistortion"):
        if (work / name).exists():
            shutil.move(str(work / name), str(aside / name))
    for name in ("images", "sparse", "masks"):
        shutil.rmtree(out / name, ignore_errors=True)
    return aside


def capture_scene(source: str | Path, out: str | Path, max_size: int = 800, frames: int = 100,
                  progress: Progress | None = None, keep_work: bool = False,
                  up: str | list | None = None, matcher: str = "auto") -> CaptureSummary:
    """Reconstruct ``source`` (a photo folder or a video) into the COLMAP scene ``out``; ``up``: the
    scene's up axis (``pipeline.data.orientation``: a method or a vector; None: the cameras');
    ``matcher``: auto (exhaustive up to ``EXHAUSTIVE_UP_TO`` photos, else loop, sequential for a
    video; a loop-matched model that fails the geometry check is matched again exhaustively) or one
    of exhaustive, loop, sequential (no second attempt)."""
    from pipeline.data.orientation import parse_up
    source, out = Path(source), Path(out)
    say = progress or (lambda line: None)
    try:
        up = parse_up(up)
    except ValueError as err:
        raise CaptureError(f"--up: {err}") from None
    if matcher not in MATCHERS:
        raise CaptureError(f"--matcher: {matcher!r} is not one of {', '.join(MATCHERS)}")
    if out.exists() and any(out.iterdir()):
        raise CaptureError(f"{out}: the output folder exists and is not empty (choose a new --out)")
    if max_size < 64:
        raise CaptureError(f"max_size must be at least 64 px, got {max_size}")
    out.mkdir(parents=True, exist_ok=True)
    work = out / "_capture_work"
    seconds: dict[str, float] = {}
    start = time.perf_counter()
    first_try = None
    try:
        names, chosen, masks = prepare_inputs(source, work, max_size, frames, say)
        chosen = chosen if matcher == "auto" else matcher
        seconds["inputs"] = round(time.perf_counter() - start, 1)
        mapped = map_once(source, work, out, names, chosen, masks, say, seconds)
        if matcher == "auto" and chosen == "loop" and mapped.geometry["verdict"] != "consistent":
            first_try = {"matcher": "loop", "pairs": pair_count(names, "loop"), "registered": len(mapped.registered),
                         "geometry": mapped.geometry, "seconds": dict(seconds)}
            say(f"the loop-matched model failed the geometry check: matching every pair "
                f"({pair_count(names, 'exhaustive')} pairs) and mapping again ...")
            retry_exhaustive(work, out)
            chosen = "exhaustive"
            mapped = map_once(source, work, out, names, chosen, masks, say, seconds)
    except BaseException:
        if not keep_work:
            shutil.rmtree(out, ignore_errors=True)
        raise
    if not keep_work:
        shutil.rmtree(work, ignore_errors=True)
    seconds["total"] = round(time.perf_counter() - start, 1)
    oriented = orient(out, up, say)
    model = mapped.model
    summary = CaptureSummary(str(source), str(out), len(names), len(mapped.registered), model.num_points3D(),
                             round(float(model.compute_mean_reprojection_error()), 4), "SIMPLE_RADIAL -> PINHOLE",
                             chosen, seconds, mapped.missing, mapped.others, masks, pair_count(names, chosen),
                             mapped.geometry, oriented, first_try)
    (out / "capture.json").write_text(json.dumps(summary.to_dict(), indent=1) + "\n")
    return summary
