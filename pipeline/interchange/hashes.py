"""The two sha256 conventions of ``result.json`` and benchmark definitions, written down once:

- an image on disk (a ground-truth test view): sha256 of the file's bytes, as ``sha256sum`` prints;
- a render: sha256 of its pixels as uint8 RGB, ``round(clip(x, 0, 1) * 255)``, rows top to
  bottom, [H, W, 3] C order, no header (independent of how the image is encoded or stored).
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np


def file_sha256(path: str | Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def to_uint8(pixels: np.ndarray) -> np.ndarray:
    """[H, W, 3] floats in [0, 1] -> uint8 by round(clip(x, 0, 1) * 255) (uint8 passes through)."""
    if pixels.ndim != 3 or pixels.shape[-1] != 3:
        raise ValueError(f"expected an [H, W, 3] image, got shape {pixels.shape}")
    if pixels.dtype == np.uint8:
        return np.ascontiguousarray(pixels)
    return np.ascontiguousarray(np.floor(np.clip(pixels.astype(np.float64), 0.0, 1.0) * 255.0 + 0.5)
                                .astype(np.uint8))


def pixels_sha256(pixels: np.ndarray) -> str:
    return hashlib.sha256(to_uint8(pixels).tobytes()).hexdigest()
