"""The scene formats, one registry line each: how a folder is recognised, which reader reads it,
and the scene's traits the protocols and the pose space need. A new format is one reader module
and one line in ``READERS``; nothing else asks which format a scene has.

| format | recognised by | split | up axis | kind |
|---|---|---|---|---|
| blender | ``transforms_train.json`` | the files' train / test | +z | object (the whole shell around it) |
| nerfstudio | ``transforms.json`` | LLFF hold-out (every 8th frame in name order) | estimated from the cameras | unbounded |
| colmap | ``sparse/`` | LLFF hold-out | estimated from the cameras | unbounded |

A captured object (``gopre-data capture``) is a COLMAP scene: its up axis is estimated from the
cameras as for bonsai (the mean of the cameras' up directions: photos are taken upright), and its default target manifold is the
protocols' 120-degree clockwise sector of azimuth about that axis, from the world x axis. Its
cameras stand inside the box of its points (a gallery's walls are in the model), so its pose space
is not bounded by a scene radius, as for every real capture.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from pipeline.data.images import DataError
from pipeline.data.scene import OBJECT, REAL, Scene, SceneTraits, traits_of  # noqa: F401 (the traits' public names)


@dataclass(frozen=True)
class SceneReader:
    format: str
    recognise: Callable[[Path], bool]
    read: Callable[..., Scene]          # read(path, width=None, masks=False) -> Scene
    traits: SceneTraits
    marker: str                         # what the folder must hold, for the error message


def _blender(path: Path, width: int | None = None, masks: bool = False) -> Scene:
    from pipeline.data.blender import read_blender
    return read_blender(path, width=width)


def _colmap(path: Path, width: int | None = None, masks: bool = False) -> Scene:
    from pipeline.data.colmap import read_colmap
    return read_colmap(path, width=width, masks=masks)


def _nerfstudio(path: Path, width: int | None = None, masks: bool = False) -> Scene:
    from pipeline.data.nerfstudio import read_nerfstudio
    return read_nerfstudio(path, width=width, masks=masks)


READERS = (
    SceneReader("blender", lambda p: (p / "transforms_train.json").exists(), _blender, traits_of("blender"),
                "transforms_train.json"),
    SceneReader("nerfstudio", lambda p: (p / "transforms.json").exists(), _nerfstudio, traits_of("nerfstudio"),
                "transforms.json"),
    SceneReader("colmap", lambda p: (p / "sparse").exists(), _colmap, traits_of("colmap"), "sparse/"),
)
BY_FORMAT = {r.format: r for r in READERS}


def reader_for(path: Path) -> SceneReader:
    for reader in READERS:
        if reader.recognise(path):
            return reader
    markers = ", ".join(f"{r.format} ({r.marker})" for r in READERS)
    raise DataError(f"{path}: not a scene folder of any known format: {markers}")
