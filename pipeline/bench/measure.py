"""Timing and memory helpers shared by the benchmarks."""

from __future__ import annotations

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
