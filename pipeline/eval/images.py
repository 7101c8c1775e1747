"""Image helpers for what a run writes and the viewer shows: uint8 conversion, PNG bytes, a
colour map for non-negative maps (errors, variances)."""

from __future__ import annotations

import io

import numpy as np
import torch
from PIL import Image


def to_uint8(image: torch.Tensor) -> np.ndarray:
    """[H, W, 3] in [0, 1] -> uint8 array."""
    return (image.detach().clamp(0, 1).cpu().numpy() * 255 + 0.5).astype(np.uint8)


def png_bytes(image: torch.Tensor) -> bytes:
    """[H, W, 3] in [0, 1] -> PNG bytes."""
    buf = io.BytesIO()
    Image.fromarray(to_uint8(image)).save(buf, format="PNG")
    return buf.getvalue()


def colormap(values: torch.Tensor) -> torch.Tensor:
    """[H, W] non-negative -> [H, W, 3] (black -> red -> yellow -> white), scaled to the 99th
    percentile so a few extreme pixels do not hide the rest."""
    top = torch.quantile(values.flatten().double(), 0.99).to(values.dtype)
    v = (values / top.clamp_min(1e-12)).clamp(0, 1)
    return torch.stack([(3 * v).clamp(0, 1), (3 * v - 1).clamp(0, 1), (3 * v - 2).clamp(0, 1)], -1)
