"""The first sweep on a machine compiles the CPU kernels (numba; cached on disk afterwards), which
used to be minutes of silence after the launch. When the cache is missing, the driver says so,
compiles them with a tiny episode before any job starts (so no job's timings carry it), and says
how long it took; later launches find the cache and skip this.

numba compiles one function at a time on one core. With two cores or more the compile is split:
the training paths (a tiny random episode: render, loss, training and evaluation kernels) and the
selection paths (a tiny gopre round: the Fishers' walk and diagonal kernels) compile at once in two
processes, each filling the same disk cache; the tiny gopre episode then runs here and compiles
whatever neither part reached (its own line says how much that was).
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable

KERNEL_MODULES = ("pipeline.splat.kernels", "pipeline.splat.project_kernels", "pipeline.fisher.diagonal_kernels",
                  "pipeline.fit.loss_kernels")
EXPECTED_WAIT = "about 2 min on 2 cores"  # measured idle from an empty cache: 105 s in two parts at once (125 s serial)


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


def _tiny_episode(strategy: str) -> None:
    """A tiny episode of ``strategy`` on a tiny generated scene (every path such an episode takes)."""
    from pipeline.active import run_episode, tiny_episode
    from pipeline.data.load import load_scene
    from pipeline.data.synthetic import generate
    with tempfile.TemporaryDirectory() as tmp:
        scene_dir = generate(Path(tmp) / "scene", seed=0, size=32, n_train=8, n_test=3)
        cfg = tiny_episode(strategy=strategy)
        run_episode(load_scene(scene_dir, width=cfg.fit.image_width), cfg)


def _selection_round() -> None:
    """One gopre round on a random model (the selection's kernels without any training)."""
    import torch

    from pipeline.acquisition import SelectionContext, make_strategy
    from pipeline.splat.scenes import random_scene, sphere_cameras
    model = random_scene(400, seed=0)
    pool, taken, probes = (sphere_cameras(n, 32, 32, seed=s) for n, s in ((6, 1), (2, 2), (3, 3)))
    ctx = SelectionContext(model, pool, list(range(len(pool))), taken, torch.ones(3),
                           torch.Generator().manual_seed(0), probes)
    make_strategy("gopre").select(ctx)


PARTS: dict[str, Callable[[], None]] = {"training": lambda: _tiny_episode("random"), "selection": _selection_round}


def _run_parts(say: Callable[[str], None]) -> None:
    """The parts at once, one process and one thread each; a part that fails is said, and leaves
    more for the tiny episode that follows."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "1"}
    workers = {name: subprocess.Popen([sys.executable, "-m", "pipeline.experiment.warmup", "--part", name],
                                      env=env, stdout=subprocess.DEVNULL) for name in PARTS}
    for name, worker in workers.items():
        if worker.wait() != 0:
            say(f"the kernels' {name} part failed (exit {worker.returncode}); the episode compiles what it left")


def compile_kernels(say: Callable[[str], None], cores: int | None = None) -> float | None:
    """Compile the kernels now if their cache is missing: the parts at once where there are two
    cores or more, then a tiny gopre episode on a tiny generated scene (every path an episode takes);
    the seconds it took, None when nothing was needed."""
    from pipeline.splat.compiled import DISABLE_ENV, compile_seconds, load
    if os.environ.get(DISABLE_ENV, "") not in ("", "0") or kernels_cached():
        return None
    say(f"compiling the CPU kernels for this machine, once ({EXPECTED_WAIT}; cached for every later run) ...")
    if load() is None:
        return None
    parallel = (len(os.sched_getaffinity(0)) if cores is None else cores) >= 2
    start = time.perf_counter()
    if parallel:
        _run_parts(say)
    parts, compiling = time.perf_counter() - start, compile_seconds()
    _tiny_episode("gopre")
    seconds = time.perf_counter() - start
    left = compile_seconds() - compiling
    say(f"compiled the CPU kernels in {seconds:.0f} s (" +
        (f"{len(PARTS)} parts at once {parts:.0f} s, then the episode compiled {left:.0f} s of what they left)"
         if parallel else f"{left:.0f} s of it numba's)"))
    return seconds


def main(argv: list[str] | None = None) -> int:
    """``python -m pipeline.experiment.warmup`` (``make env`` runs it): compile and cache the kernels
    now, so that neither the first sweep nor the test suite's workers wait for them. ``--serial``:
    one process (the compile as it was, to compare); ``--part NAME``: one part only (the parallel
    compile's workers)."""
    parser = argparse.ArgumentParser(prog="python -m pipeline.experiment.warmup")
    parser.add_argument("--part", choices=sorted(PARTS))
    parser.add_argument("--serial", action="store_true")
    args = parser.parse_args(argv)
    if args.part:
        import torch
        torch.set_num_threads(1)
        PARTS[args.part]()
        return 0
    seconds = compile_kernels(lambda line: print(line, flush=True), cores=1 if args.serial else None)
    if seconds is None:
        print("the CPU kernels are compiled and cached already (or disabled): nothing to do")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
