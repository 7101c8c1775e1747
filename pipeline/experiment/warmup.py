"""The first sweep on a machine compiles the CPU kernels (numba; cached on disk afterwards), which
used to be minutes of silence after the launch. When the cache is missing, the driver says so,
compiles them with a tiny episode before any job starts (so no job's timings carry it), and says
how long it took; later launches find the cache and skip this."""

from __future__ import annotations

import importlib.util
import os
import tempfile
import time
from pathlib import Path
from typing import Callable

KERNEL_MODULES = ("pipeline.splat.kernels", "pipeline.splat.project_kernels", "pipeline.fisher.diagonal_kernels",
                  "pipeline.fit.loss_kernels")
EXPECTED_WAIT = "about 2-3 min on 2 cores"  # measured on a fresh clone, idle: 137-141 s


def kernels_cached() -> bool:
    """Whether numba's disk cache holds every kernel module's index (``<module>.*.nbi``)."""
    cache_dir = os.environ.get("NUMBA_CACHE_DIR")
    for name in KERNEL_MODULES:
        spec = importlib.util.find_spec(name)
        if spec is None or spec.origin is None:
            return False
        source = Path(spec.origin)
        folder = Path(cache_dir) if cache_dir else source.parent / "__pycache__"
        if not any(folder.glob(f"{source.stem}.*.nbi")):
            return False
    return True


def compile_kernels(say: Callable[[str], None]) -> float | None:
    """Compile the kernels now if their cache is missing (a tiny gopre episode on a tiny generated
    scene runs every path an episode takes); the seconds it took, None when nothing was needed."""
    from pipeline.splat.compiled import DISABLE_ENV, compile_seconds, load
    if os.environ.get(DISABLE_ENV, "") not in ("", "0") or kernels_cached():
        return None
    say(f"compiling the CPU kernels for this machine, once ({EXPECTED_WAIT}; cached for every later run) ...")
    if load() is None:
        return None
    from pipeline.active import run_episode, tiny_episode
    from pipeline.data.load import load_scene
    from pipeline.data.synthetic import generate
    start, compiling = time.perf_counter(), compile_seconds()
    with tempfile.TemporaryDirectory() as tmp:
        scene_dir = generate(Path(tmp) / "scene", seed=0, size=32, n_train=8, n_test=3)
        cfg = tiny_episode(strategy="gopre")
        run_episode(load_scene(scene_dir, width=cfg.fit.image_width), cfg)
    seconds = time.perf_counter() - start
    say(f"compiled the CPU kernels in {seconds:.0f} s ({compile_seconds() - compiling:.0f} s of it numba's)")
    return seconds


def main() -> int:
    """``python -m pipeline.experiment.warmup`` (``make env`` runs it): compile and cache the kernels
    now, so that neither the first sweep nor the test suite's workers wait for them."""
    seconds = compile_kernels(lambda line: print(line, flush=True))
    if seconds is None:
        print("the CPU kernels are compiled and cached already (or disabled): nothing to do")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
