"""Timing and memory helpers shared by the benchmarks."""

from __future__ import annotations

from contextlib import contextmanager

import os
import statistics
import time
from typing import Callable

from pipeline.memory import peak_rss_mb, reset_peak_rss  # noqa: F401 (re-exported)


def median_seconds(fn: Callable[[], object], repeats: int, warmup: int = 1) -> float:
    """Median wall time of ``fn`` over ``repeats`` runs after ``warmup`` untimed runs."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def available_memory_mb() -> float:
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return float("inf")


def machine_load() -> float:
    return os.getloadavg()[0]


BACKEND_VARIANTS = ("tiles", "compiled-unfused", "compiled")


@contextmanager
def backend_variant(name: str):
    """Within the block ``auto`` resolves to the variant's backend: ``tiles`` (the torch path),
    ``compiled`` (the production path, fused paths on) or ``compiled-unfused`` (the compiled ops
    without the fused paths: the production path before them), for before/after in one process."""
    from pipeline.splat.compiled import auto_backend, fused_paths
    if name not in BACKEND_VARIANTS:
        raise ValueError(f"backend variant must be one of {BACKEND_VARIANTS}, got {name!r}")
    with auto_backend(name.removesuffix("-unfused")), fused_paths(name != "compiled-unfused"):
        yield
