"""Read a scene folder whatever its layout (Blender or COLMAP), detected from its files."""

from __future__ import annotations

from pathlib import Path

from pipeline.data.images import DataError
from pipeline.data.scene import Scene


def load_scene(path: str | Path, width: int | None = None) -> Scene:
    """A Blender-layout scene (transforms_train.json) or a COLMAP scene (sparse/), at ``width``."""
    from pipeline.data.blender import read_blender
    from pipeline.data.colmap import read_colmap

    path = Path(path)
    if not path.exists():
        raise DataError(f"{path}: no such folder")
    if (path / "transforms_train.json").exists():
        return read_blender(path, width=width)
    if (path / "sparse").exists():
        return read_colmap(path, width=width)
    raise DataError(f"{path}: neither a Blender scene (transforms_train.json) nor a COLMAP scene (sparse/)")
