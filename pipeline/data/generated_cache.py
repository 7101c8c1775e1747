"""Generated scenes kept by what makes their bytes, so that a scene is ray-cast once per machine
instead of once per output folder.

The embedded scene is a function of its settings (``GeneratedScene``), of the generator's source and
of the libraries that compute and encode its pixels (torch, scikit-image's textures, Pillow's PNG
writer). With a cache folder (``GOPRE_SCENE_CACHE``), a sweep that needs a scene it does not have
copies it from ``<cache>/<key>``, generating it there first when absent; without one it generates
in place as before. The copy is byte-identical to a generated scene, so its data fingerprint is the
same (tested). The test suite sets the variable for its session (tests/conftest.py): a tiny scene
cost 8 s of ray casting in every test that ran a sweep.
"""

from __future__ import annotations

import os
import shutil
from dataclasses import asdict, astuple
from pathlib import Path
from typing import Callable

from pipeline.data.fingerprint import generator_identity
from pipeline.data.synthetic import GeneratedScene, generate, move_into_place

CACHE_ENV = "GOPRE_SCENE_CACHE"


def cache_from_environment() -> Path | None:
    """The cache folder ``GOPRE_SCENE_CACHE`` names, or None (no cache) when it is unset or empty."""
    value = os.environ.get(CACHE_ENV, "").strip()
    return Path(value) if value else None


def cache_key(settings: GeneratedScene) -> str:
    """The folder name of a scene in the cache: its settings, readable, and the generator's identity."""
    seed, size, n_train, n_test = astuple(settings)
    return f"generated-{size}px-{n_train}-{n_test}-seed{seed}-{generator_identity()}"


def place_generated(target: str | Path, settings: GeneratedScene, cache: Path | None,
                    progress: Callable[[str, int, int], None] | None = None) -> Path:
    """The generated scene of ``settings`` at ``target``: copied from ``cache`` (generated into it
    first when absent), or generated at ``target`` when ``cache`` is None."""
    if cache is None:
        return generate(target, **asdict(settings), progress=progress)
    kept = cache / cache_key(settings)
    if not (kept / "transforms_test.json").is_file():  # generate() renames a finished scene into place
        generate(kept, **asdict(settings), progress=progress)
    final = Path(target)
    partial = final.parent / f".{final.name}.copy-{os.getpid()}"
    if partial.exists():
        shutil.rmtree(partial)
    final.parent.mkdir(parents=True, exist_ok=True)
    shutil.copytree(kept, partial)
    move_into_place(partial, final)
    return final

