"""How much a paired difference says, beside its interval: the effect size and the seeds a paired
test would need to resolve it.

- effect size d_z = mean(d) / sd(d) (sd with n - 1), the standardized mean of the paired differences
  d (Cohen's d for paired samples);
- seeds needed: the smallest number n of pairs at which a two-sided paired t-test at level
  ``ALPHA`` rejects "no difference" with probability ``POWER`` when the true effect is the observed
  d_z; the power is exact under normality, from the noncentral t distribution (noncentrality
  d_z sqrt(n), n - 1 degrees of freedom), as G*Power computes it.

A reader then sees whether "not testable" means no effect (d_z near 0: thousands of seeds) or too few
seeds (a large d_z measured on 3 pairs: 6 would do). The verdicts themselves stay the bootstrap
interval's (``stats.verdict``); this is planning, not a second test.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.stats import nct, t

ALPHA = 0.05
POWER = 0.8
MAX_SEEDS = 10_000  # beyond this the answer is "more than MAX_SEEDS": no effect worth seeds


def effect_size(differences) -> float | None:
    """d_z of the paired differences; None with fewer than 2 or when they are all equal
    (no spread to scale by)."""
    d = np.asarray(differences, dtype=float)
    if d.size < 2:
        return None
    sd = float(d.std(ddof=1))
    return None if sd == 0 else float(d.mean() / sd)


def paired_t_power(dz: float, n: int, alpha: float = ALPHA) -> float:
    """Power of the two-sided paired t-test with ``n`` pairs at true effect ``dz``."""
    if n < 2:
        return 0.0
    df, shift = n - 1, dz * math.sqrt(n)
    critical = t.ppf(1 - alpha / 2, df)
    return float(nct.sf(critical, df, shift) + nct.cdf(-critical, df, shift))


def seeds_needed(dz: float | None, alpha: float = ALPHA, power: float = POWER) -> int | None:
    """The smallest number of pairs with ``paired_t_power`` >= ``power``; None when ``dz`` is None,
    0 or would need more than ``MAX_SEEDS``."""
    if dz is None or dz == 0 or not math.isfinite(dz):
        return None
    lo, hi = 2, 2
    while paired_t_power(dz, hi, alpha) < power:  # double, then bisect (the power grows with n)
        lo, hi = hi, hi * 2
        if hi > MAX_SEEDS:
            return None
    while lo < hi:
        mid = (lo + hi) // 2
        if paired_t_power(dz, mid, alpha) >= power:
            hi = mid
        else:
            lo = mid + 1
    return hi
