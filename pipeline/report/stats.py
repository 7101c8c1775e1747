"""Statistics for comparing methods across seeds: the PSNR-vs-views area, and paired differences
against a reference method with bootstrap intervals and wins/losses.

A pair is one (dataset, scene, seed, setting) on which both the method and the reference finished:
the same scene, the same initial views and the same seed, so the difference removes what the
seed shares between methods. The interval is scipy's BCa bootstrap over pairs (seeded, so a
report is reproducible), with the Wilcoxon signed-rank p-value, the effect size d_z and the seeds a
paired t-test would need for 80% power at it (``power``) beside it.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy.stats import bootstrap, wilcoxon

from pipeline.report.power import effect_size, seeds_needed

PAIR_KEYS = ("dataset", "scene", "seed", "setting")
BOOTSTRAP_SAMPLES = 10_000
TIE_DB = 1e-9  # differences this small count as ties
MIN_PAIRS = 5  # fewer pairs: the interval is printed but no verdict is drawn from it


def curve_area(num_views: np.ndarray, psnr: np.ndarray) -> float:
    """Area under the PSNR-vs-views curve divided by its span of views: the curve's mean PSNR in
    dB (trapezoid rule over the recorded view counts); the single value when there is one."""
    order = np.argsort(num_views, kind="stable")
    x, y = np.asarray(num_views, dtype=float)[order], np.asarray(psnr, dtype=float)[order]
    if len(x) == 1 or x[-1] == x[0]:
        return float(y.mean())
    return float(np.sum((x[1:] - x[:-1]) * (y[1:] + y[:-1]) / 2) / (x[-1] - x[0]))


def job_keys(frame: pd.DataFrame) -> list[str]:
    """What names one job's rows: its config hash within its sweep (two sweeps compared side by
    side may hold the same job, e.g. the same config under two code versions)."""
    return [k for k in ("sweep", "config_hash") if k in frame]


def job_ids(frame: pd.DataFrame, keys: list[str]) -> list[tuple]:
    """Each row's job as a tuple of its ``keys`` values: the form ``frame.groupby(keys)`` names a
    group in, whatever the number of keys."""
    return list(frame[keys].itertuples(index=False, name=None))


def with_curve_area(final: pd.DataFrame, rounds: pd.DataFrame) -> pd.DataFrame:
    """``final`` with a ``psnr_auc`` column: each job's curve area from its rounds."""
    if rounds.empty:
        return final.assign(psnr_auc=np.nan)
    keys = job_keys(rounds)
    areas = {key: curve_area(part["num_views"].to_numpy(), part["psnr"].to_numpy())
             for key, part in rounds.dropna(subset=["psnr"]).groupby(keys)}
    return final.assign(psnr_auc=[areas.get(job, np.nan) for job in job_ids(final, keys)])


def bootstrap_interval(values: np.ndarray, level: float = 0.95, samples: int = BOOTSTRAP_SAMPLES,
                       seed: int = 0) -> tuple[float, float]:
    """Bias-corrected and accelerated (BCa) bootstrap interval of the mean of ``values`` [n]
    (``scipy.stats.bootstrap``, seeded so a report is reproducible). Values that are all equal
    (or n = 1) give a zero-width interval, which the tables flag by n; if BCa is undefined for a
    sample (its jackknife is degenerate) the percentile interval is used."""
    values = np.asarray(values, dtype=float)
    if values.size == 0:
        raise ValueError("bootstrap_interval: no values")
    if values.size == 1 or np.ptp(values) == 0:
        return float(values.mean()), float(values.mean())
    for method in ("BCa", "percentile"):
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore")  # BCa's degenerate-jackknife warning: handled below
            ci = bootstrap((values,), np.mean, confidence_level=level, n_resamples=samples,
                           method=method, random_state=np.random.default_rng(seed)).confidence_interval
        if np.isfinite(ci.low) and np.isfinite(ci.high):
            return float(ci.low), float(ci.high)
    return float(values.mean()), float(values.mean())


def wilcoxon_p(differences: np.ndarray) -> float | None:
    """Two-sided Wilcoxon signed-rank p-value of paired differences (zero differences dropped);
    None when no difference is non-zero."""
    d = np.asarray(differences, dtype=float)
    d = d[np.abs(d) > TIE_DB]
    if d.size == 0:
        return None
    return float(wilcoxon(d).pvalue)


@dataclass
class PairedComparison:
    method: str
    reference: str
    metric: str
    n: int                      # pairs
    mean_difference: float      # method - reference (for PSNR: positive = method better)
    low: float                  # 95% bootstrap interval of the mean difference
    high: float
    wins: int                   # pairs where the method is better than the reference
    losses: int
    ties: int
    wilcoxon_p: float | None = None  # two-sided signed-rank test of the differences
    effect_size: float | None = None  # d_z = mean / sd of the differences (``power``)
    seeds_needed: int | None = None   # pairs a paired t-test needs for 80% power at d_z (None: > MAX_SEEDS)


def default_reference(methods: list[str], reference: str | None = None) -> str | None:
    """The method paired comparisons are against: ``reference`` when given, else gopre when it ran."""
    if reference is not None:
        return reference
    return "gopre" if "gopre" in methods else None


def paired_differences(final: pd.DataFrame, reference: str, metric: str,
                       higher_is_better: bool = True) -> dict[str, np.ndarray]:
    """Per method other than ``reference``: method - reference over the pairs both finished."""
    keys = [k for k in PAIR_KEYS if k in final]
    data = final.dropna(subset=[metric]).copy()
    data["setting"] = data["setting"].fillna("") if "setting" in data else ""
    table = data.pivot_table(index=keys, columns="method", values=metric, aggfunc="mean")
    if reference not in table:
        raise ValueError(f"reference method {reference!r} has no finished runs with {metric!r}; "
                         f"methods: {sorted(table.columns)}")
    out = {}
    for method in table.columns:
        if method == reference:
            continue
        both = table[[method, reference]].dropna()
        diff = (both[method] - both[reference]).to_numpy(dtype=float)
        out[method] = diff if higher_is_better else -diff
    return out


def paired_comparisons(final: pd.DataFrame, reference: str, metric: str = "psnr",
                       method_order: list[str] | None = None,
                       higher_is_better: bool = True) -> list[PairedComparison]:
    """One ``PairedComparison`` per method with at least one pair, in ``method_order``."""
    diffs = paired_differences(final, reference, metric, higher_is_better)
    order = [m for m in (method_order or list(diffs)) if m in diffs]
    out = []
    for method in order:
        d = diffs[method]
        if d.size == 0:
            continue
        low, high = bootstrap_interval(d)
        dz = effect_size(d)
        out.append(PairedComparison(method, reference, metric, int(d.size), float(d.mean()), low, high,
                                    int((d > TIE_DB).sum()), int((d < -TIE_DB).sum()),
                                    int((np.abs(d) <= TIE_DB).sum()), wilcoxon_p(d), dz, seeds_needed(dz)))
    return out


def verdict(c: PairedComparison) -> str:
    """Plain words: whether the interval excludes zero, and on which side; no verdict from fewer
    than ``MIN_PAIRS`` pairs (a bootstrap over 2-4 values is far too narrow)."""
    if c.n < MIN_PAIRS:
        return f"{c.n} pair(s): too few for a verdict"
    if c.low > 0:
        return f"{c.method} better"
    if c.high < 0:
        return f"{c.reference} better"
    return "no clear difference"
