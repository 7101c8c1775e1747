"""Read a scene folder whatever its layout, recognised by its files (``pipeline.data.readers``)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from pipeline.data.images import DataError
from pipeline.data.readers import reader_for
from pipeline.data.scene import Scene


def load_scene(path: str | Path, width: int | None = None, masks: bool = False) -> Scene:
    """The scene in ``path`` at ``width``, with its format's traits; ``masks``: read the capture's
    masks (an error naming the folder when it has none)."""
    path = Path(path)
    if not path.exists():
        raise DataError(f"{path}: no such folder")
    reader = reader_for(path)
    scene = reader.read(path, width=width, masks=masks)
    return replace(scene, traits=reader.traits)
