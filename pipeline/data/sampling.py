"""Seeded sampling rules of the protocols and the episode: a subset of view ids, the probe count K
and its draw, the random candidate-pool reduction. Pure functions of (ids, count, generator), so a
draw does not depend on the order the ids come in."""

from __future__ import annotations

import torch


def reduce_pool(candidate_ids: list[int], keep_fraction: float, generator: torch.Generator) -> list[int]:
    """Candidate-pool reduction: keep a seeded random ``keep_fraction`` (at least one) of the pool."""
    if not 0 < keep_fraction <= 1:
        raise ValueError(f"keep_fraction must be in (0, 1], got {keep_fraction}")
    return seeded_subset(candidate_ids, max(1, round(len(candidate_ids) * keep_fraction)), generator)


def probe_count(k: int | float, views: int) -> int:
    """Number of probe poses K: an int is used as is (capped at ``views``), a float in (0, 1) is
    a fraction of ``views`` (the paper: 25 for Blender, 1/8 of all N views of a real scene,
    Table 5: N/4 ... N/64); >= 1."""
    if isinstance(k, float) and 0 < k < 1:
        return max(1, round(k * views))
    if int(k) < 1:
        raise ValueError(f"probe count must be >= 1 or a fraction in (0, 1), got {k}")
    return min(int(k), views)


def sample_probes(pool_ids: list[int], k: int | float, generator: torch.Generator) -> list[int]:
    """K probe view ids drawn uniformly without replacement from the target-manifold pool."""
    if not pool_ids:
        raise ValueError("sample_probes: the target manifold has no views to probe")
    return seeded_subset(pool_ids, probe_count(k, len(pool_ids)), generator)


def seeded_subset(ids: list[int], count: int, generator: torch.Generator) -> list[int]:
    """``count`` of ``ids`` drawn uniformly without replacement, sorted; independent of the order
    ``ids`` come in (the draw indexes the sorted ids)."""
    ids = sorted(ids)
    picked = torch.randperm(len(ids), generator=generator)[:count].sort().values
    return [ids[i] for i in picked.tolist()]
