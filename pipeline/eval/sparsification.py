"""Sparsification curves and AUSE (Ilg et al. 2018), over whole test views as in the paper.

Views are sorted by predicted uncertainty, most uncertain first; the curve at fraction f is the
mean quality (PSNR, higher is better) of the views left after removing the first round(f V).
The oracle removes the truly worst views first, so its curve is the highest possible; AUSE is
the area between the oracle's curve and a method's, by the trapezoid rule over the fractions
(deciles 0, 0.1, ..., 0.9 by default). A well-calibrated method's curve rises like the oracle's.
"""

from __future__ import annotations

import numpy as np

DECILES = tuple(i / 10 for i in range(10))


def _as_vectors(quality, uncertainty) -> tuple[np.ndarray, np.ndarray]:
    q, u = np.asarray(quality, dtype=np.float64), np.asarray(uncertainty, dtype=np.float64)
    if q.ndim != 1 or q.shape != u.shape or len(q) == 0:
        raise ValueError(f"quality and uncertainty must be equal-length vectors, got {q.shape}, {u.shape}")
    if not (np.isfinite(q).all() and np.isfinite(u).all()):
        raise ValueError("quality and uncertainty must be finite")
    return q, u


def sparsification_curve(quality, uncertainty, fractions=DECILES) -> np.ndarray:
    """Mean quality [F] of the views kept after removing the most uncertain fraction f of them.

    Ties in uncertainty keep the given view order (stable sort)."""
    q, u = _as_vectors(quality, uncertainty)
    order = np.argsort(-u, kind="stable")
    out = []
    for f in fractions:
        if not 0 <= f < 1:
            raise ValueError(f"fractions must lie in [0, 1), got {f}")
        out.append(q[order[int(round(f * len(q))):]].mean())
    return np.array(out)


def oracle_curve(quality, fractions=DECILES) -> np.ndarray:
    """The curve of the ranking by true quality (worst views removed first)."""
    q = np.asarray(quality, dtype=np.float64)
    return sparsification_curve(q, -q, fractions)


def random_curve(quality, seed: int = 0, fractions=DECILES) -> np.ndarray:
    """The curve of a seeded random ranking (the uninformed baseline)."""
    q = np.asarray(quality, dtype=np.float64)
    return sparsification_curve(q, np.random.default_rng(seed).permutation(len(q)).astype(float), fractions)


def ause(curve, oracle, fractions=DECILES) -> float:
    """Area between the oracle's curve and ``curve`` (quality curves), trapezoid over fractions."""
    c, o, x = (np.asarray(v, dtype=np.float64) for v in (curve, oracle, fractions))
    if not c.shape == o.shape == x.shape:
        raise ValueError(f"curve {c.shape}, oracle {o.shape} and fractions {x.shape} must match")
    d = o - c
    return float(np.sum((d[1:] + d[:-1]) * np.diff(x) / 2))
