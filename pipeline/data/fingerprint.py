"""A scene's data identity: one digest of every file a reader takes from the scene folder.

What a reader reads, per format (the sources, listed without decoding an image):

| format | model files | images |
|---|---|---|
| colmap | ``cameras``, ``images``, ``points3D`` (and ``rigs``, ``frames``) ``.bin``/``.txt`` of its sparse model, ``capture.json`` (a capture's up axis) | every file in ``images/`` (and ``masks/`` when the job reads masks) |
| blender | ``transforms_{train,val,test}.json`` | every frame those files name |
| nerfstudio | ``transforms.json`` | every frame's ``file_path`` (and ``mask_path`` when read), ``ply_file_path`` |

The generated scene has no files until it is cast: its identity is its options and the generator that
makes its files from them (``generated_fingerprint``: the generator's source and the versions of the
libraries behind its pixels), so a changed generator is other data, as a changed file is.

The digest is the sha256 of the lines ``<path relative to the scene folder>\\t<sha256 of the file>``
in path order, so the same bytes at another path (another node's mount, a copied folder) give the
same fingerprint and any changed, added or removed file gives another. A file's sha256 is cached by
(absolute path, size, mtime) in ``GOPRE_CACHE/file_digests.json`` (default ``~/.cache/gopre``), so a
launch does not re-read a large scene whose files did not change.
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import os
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path

from pipeline.data.images import DataError
from pipeline.interchange.hashes import file_sha256

MODEL_STEMS = ("cameras", "images", "points3D", "rigs", "frames")
IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp"}
SHOWN = 16  # hex digits of a fingerprint that jobs, records, tags and tables carry
GENERATOR = "pipeline.data.synthetic"  # the module that casts the generated scene
GENERATOR_LIBRARIES = ("torch", "scikit-image", "Pillow", "numpy")  # what computes and encodes its pixels


@dataclass(frozen=True)
class DataFingerprint:
    """The identity of a scene's data: ``digest`` (sha256 hex of the file list), how many files and bytes."""

    digest: str
    files: int
    bytes: int

    @property
    def short(self) -> str:
        return self.digest[:SHOWN]


def cache_path() -> Path:
    return Path(os.environ.get("GOPRE_CACHE", Path.home() / ".cache" / "gopre")) / "file_digests.json"


class FileDigests:
    """sha256 of files, remembered by (absolute path, size, mtime_ns) across processes."""

    def __init__(self, path: Path | None = None):
        self.path = path or cache_path()
        self.known: dict[str, list] = {}
        self.changed = False
        try:
            self.known = json.loads(self.path.read_text())
        except (OSError, ValueError):  # no cache yet, or a cut-short write: start empty
            self.known = {}

    def digest(self, path: Path) -> tuple[str, int]:
        """(sha256, size) of ``path``."""
        stat = path.stat()
        key = str(path.resolve())
        entry = self.known.get(key)
        if entry is not None and entry[0] == stat.st_size and entry[1] == stat.st_mtime_ns:
            return entry[2], stat.st_size
        sha = file_sha256(path)
        self.known[key] = [stat.st_size, stat.st_mtime_ns, sha]
        self.changed = True
        return sha, stat.st_size

    def save(self) -> None:
        """Write the cache atomically (a race between two processes loses entries, never the file)."""
        if not self.changed:
            return
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            tmp = self.path.with_name(f"{self.path.name}.{os.getpid()}.tmp")
            tmp.write_text(json.dumps(self.known))
            os.replace(tmp, self.path)
            self.changed = False
        except OSError:  # a read-only home: the digests are recomputed next time, nothing else changes
            pass


def _files_in(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.is_file() and not p.name.startswith(".")) \
        if folder.is_dir() else []


def _colmap_sources(root: Path, masks: bool) -> list[Path]:
    from pipeline.data.colmap import sparse_dir
    sparse = sparse_dir(root)
    model = [p for p in _files_in(sparse) if p.stem in MODEL_STEMS and p.suffix in (".bin", ".txt")]
    images = [p for p in _files_in(root / "images") if p.suffix.lower() in IMAGE_SUFFIXES]
    if not images:
        raise DataError(f"{root / 'images'}: no images to fingerprint")
    mask_files = [p for p in _files_in(root / "masks") if p.suffix.lower() in IMAGE_SUFFIXES] if masks else []
    chosen = [root / "capture.json"] if (root / "capture.json").is_file() else []  # may set the up axis
    return model + images + mask_files + chosen


def _json(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise DataError(f"{path}: cannot read ({err})") from None


def _blender_sources(root: Path, masks: bool) -> list[Path]:
    out = []
    for split in ("train", "val", "test"):
        path = root / f"transforms_{split}.json"
        if not path.exists():
            continue
        out.append(path)
        for frame in _json(path).get("frames", []):
            image = (root / str(frame.get("file_path", ""))).resolve()
            if image.suffix.lower() not in (".png", ".jpg", ".jpeg"):
                image = image.with_name(image.name + ".png")
            out.append(image)
    return out


def _nerfstudio_sources(root: Path, masks: bool) -> list[Path]:
    path = root / "transforms.json"
    meta = _json(path)
    out = [path]
    for frame in meta.get("frames", []):
        out.append((root / str(frame.get("file_path", ""))).resolve())
        if masks and frame.get("mask_path"):
            out.append((root / str(frame["mask_path"])).resolve())
    if meta.get("ply_file_path"):
        out.append((root / str(meta["ply_file_path"])).resolve())
    return out


SOURCES = {"colmap": _colmap_sources, "blender": _blender_sources, "nerfstudio": _nerfstudio_sources}


def source_files(root: str | Path, masks: bool = False) -> list[Path]:
    """Every file the scene's reader takes from ``root`` (its format recognised as the reader does)."""
    from pipeline.data.readers import reader_for
    root = Path(root)
    if not root.is_dir():
        raise DataError(f"{root}: no such folder")
    files = SOURCES[reader_for(root).format](root, masks)
    missing = [p for p in files if not p.is_file()]
    if missing:
        raise DataError(f"{missing[0]}: a file of the scene {root} is missing ({len(missing)} missing)")
    return files


def _relative(path: Path, root: Path) -> str:
    try:
        return path.resolve().relative_to(root.resolve()).as_posix()
    except ValueError:  # a frame outside the folder: its name stands for it
        return f"../{path.name}"


def scene_fingerprint(root: str | Path, masks: bool = False, digests: FileDigests | None = None) -> DataFingerprint:
    """The fingerprint of the scene in ``root`` (with its masks when the job reads them)."""
    root = Path(root)
    own = digests is None
    digests = digests or FileDigests()
    lines, total = [], 0
    for path in source_files(root, masks):
        sha, size = digests.digest(path)
        lines.append(f"{_relative(path, root)}\t{sha}")
        total += size
    if own:
        digests.save()
    lines.sort()
    digest = hashlib.sha256(("\n".join(lines) + "\n").encode()).hexdigest()
    return DataFingerprint(digest, len(lines), total)


def generator_source() -> Path:
    """The scene generator's source file, found without importing it (no torch here)."""
    spec = importlib.util.find_spec(GENERATOR)
    if spec is None or spec.origin is None:
        raise DataError(f"{GENERATOR}: the scene generator's source cannot be found (a broken install)")
    return Path(spec.origin)


def generator_identity() -> str:
    """A digest of the scene generator's source and of the versions of the libraries behind its bytes."""
    digest = hashlib.sha256(generator_source().read_bytes())
    for name in GENERATOR_LIBRARIES:
        digest.update(f"{name}={metadata.version(name)}".encode())
    return digest.hexdigest()[:16]


def generated_fingerprint(options: dict | None) -> str:
    """The generated scene's data identity: its options and the generator that makes its files from
    them (``generator_identity()``)."""
    return _generated_digest({"options": options or {}, "generator": generator_identity()})


def options_identity(options: dict | None) -> str:
    """What a generated job made before the generator entered its identity named as its data: the
    options alone (its records and result files carry this form)."""
    return _generated_digest(options or {})


def _generated_digest(payload: dict) -> str:
    text = json.dumps(payload, sort_keys=True, default=str)
    return "generated-" + hashlib.sha256(text.encode()).hexdigest()[:12]
