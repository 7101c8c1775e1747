"""What a robot would travel: the length of the path through the picked cameras, in pick order.

The path starts at the last initial view and visits each picked view's centre in the order picked
(straight segments); it is divided by the diameter of the pool's camera centres (the largest distance
between two of them), so scenes of any scale compare: 1.0 is one crossing of the capture.
"""

from __future__ import annotations

import torch
from torch import Tensor


def path_length(centres: Tensor) -> float:
    """Sum of the straight segments through ``centres`` [K, 3] in order (0 for fewer than 2)."""
    if len(centres) < 2:
        return 0.0
    c = centres.double()
    return float((c[1:] - c[:-1]).norm(dim=1).sum())


def diameter(centres: Tensor) -> float:
    """The largest distance between two of ``centres`` [C, 3]."""
    c = centres.double()
    return float(torch.cdist(c, c).max()) if len(c) > 1 else 0.0


def picked_path(taken_centres: Tensor, initial: int, pool_centres: Tensor) -> float | None:
    """The path from the last of the ``initial`` views through the picks (``taken_centres`` [K, 3]:
    the initial views, then the picks, in order), over the pool's diameter; None without a pick."""
    if len(taken_centres) <= initial or initial < 1:
        return None
    scale = diameter(pool_centres)
    return path_length(taken_centres[initial - 1:]) / scale if scale > 0 else None
