"""The compiled CPU backend: numba kernels (``kernels.py``) behind the rasterizer's contract.

``rasterize_compiled`` takes and returns what ``rasterize.rasterize`` does, with an analytic
backward (``_CompiledComposite``). Loading is lazy: the first use imports numba and the kernels
(compiled once, then cached on disk by numba between processes). A machine where that fails
falls back to the torch path; ``resolve_backend("auto", ...)`` then warns once, naming the reason.

Threads: every call runs the kernels on ``torch.get_num_threads()`` threads, capped at numba's
pool, which is sized to torch's thread count when the kernels first load (``NUMBA_NUM_THREADS``
overrides it); one thread runs them serially. Loading them leaves torch's thread count as it was.
"""

from __future__ import annotations

import os
import threading
import time
import warnings
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from typing import Callable, Iterator, TypeVar

import numpy as np
import torch
from torch import Tensor

_STATE: dict = {}
T = TypeVar("T")
_THREAD = threading.local()  # side_by_side: set in map_in_threads' threads
DISABLE_ENV = "GOPRE_DISABLE_COMPILED"  # set to 1 to force the torch fallback (tests, debugging)


def load():
    """The kernels module, or None when the compiled path cannot load (reason in ``load_error()``)."""
    compile_seconds()  # the compile clock runs from before the first kernel compiles
    if "kernels" not in _STATE:
        _STATE["kernels"], _STATE["error"] = None, None
        if os.environ.get(DISABLE_ENV, "") not in ("", "0"):
            _STATE["error"] = f"{DISABLE_ENV} is set"
        else:
            threads = torch.get_num_threads()
            try:
                from pipeline.splat import kernels
                _start_thread_pool(threads)
                _STATE["kernels"] = kernels
            except Exception as exc:  # ImportError, or numba failing to initialise
                _STATE["error"] = f"{type(exc).__name__}: {exc}"
            finally:
                torch.set_num_threads(threads)
    return _STATE["kernels"]


def _start_thread_pool(threads: int) -> None:
    """Start numba's thread pool with ``threads`` threads (unless ``NUMBA_NUM_THREADS`` says
    otherwise); the caller then restores torch's thread count.

    Sized to the job: a one-thread job gets no idle pool threads, which otherwise spin on the
    cores other jobs use. Not via the environment, which child processes (Ray workers) inherit.
    And numba's OpenMP layer sets the process-wide OpenMP thread count to its pool size, which
    silently gave every later torch op all the machine's cores (measured: a sweep of one-thread
    jobs on 2 cores ran 15x slower than the same jobs alone)."""
    import numba
    from numba.np.ufunc import parallel
    if "NUMBA_NUM_THREADS" not in os.environ and not parallel._is_initialized:
        numba.config.NUMBA_NUM_THREADS = parallel.NUM_THREADS = max(1, threads)  # type: ignore[attr-defined]
    parallel._launch_threads()


class _CompileClock:
    """Seconds this process has spent compiling numba functions (the outermost ``numba:compile``
    events: a kernel compiling the ones it calls counts once). Installed when numba is imported
    here; a kernel loaded from numba's disk cache is not a compile."""

    def __init__(self):
        self.seconds, self._depth, self._start = 0.0, {}, {}
        self._lock = threading.Lock()

    def on_start(self, event) -> None:
        key = threading.get_ident()
        with self._lock:
            depth = self._depth.get(key, 0)
            if depth == 0:
                self._start[key] = time.perf_counter()
            self._depth[key] = depth + 1

    def on_end(self, event) -> None:
        key = threading.get_ident()
        with self._lock:
            self._depth[key] = self._depth.get(key, 1) - 1
            if self._depth[key] == 0 and key in self._start:
                self.seconds += time.perf_counter() - self._start.pop(key)


def compile_seconds() -> float:
    """Seconds spent compiling numba code in this process so far (0 before numba is used here):
    what the timings of a round subtract, so a fresh machine's first round does not count its
    one-time compilation as selection or training time."""
    clock = _STATE.get("clock")
    if clock is None:
        try:
            import numba.core.event as events
        except ImportError:
            return 0.0
        clock = _CompileClock()
        listener = type("CompileListener", (events.Listener,), {
            "on_start": lambda self, event: clock.on_start(event),
            "on_end": lambda self, event: clock.on_end(event)})()
        events.register("numba:compile", listener)
        _STATE["clock"] = clock
    return clock.seconds


def load_error() -> str | None:
    load()
    return _STATE["error"]


@contextmanager
def auto_backend(name: str):
    """Within the block, ``auto`` resolves to ``name`` (``tiles`` or ``compiled``) on CPU: how the
    benchmarks time whole episodes and selection rounds on the torch path in the same process."""
    if name not in ("tiles", "compiled"):
        raise ValueError(f"auto_backend: 'tiles' or 'compiled', got {name!r}")
    before = _STATE.get("auto")
    _STATE["auto"] = name
    try:
        yield
    finally:
        _STATE["auto"] = before


@contextmanager
def fused_paths(enabled: bool):
    """Within the block, the fused compiled paths (the training step without autograd,
    ``fit.fused_step``; the Fisher's per-view diagonal and the compiled scores) are used when
    ``enabled`` (the default outside any block), else the unfused compiled ops they replace: how
    ``bench episode`` times both in one process and how the tests compare them."""
    before = _STATE.get("fused", True)
    _STATE["fused"] = bool(enabled)
    try:
        yield
    finally:
        _STATE["fused"] = before


def fused_enabled() -> bool:
    return _STATE.get("fused", True)


def resolve_backend(backend: str, device: torch.device) -> str:
    """``auto`` -> ``compiled`` for CPU tensors when it loads, else ``tiles`` (one warning when the
    compiled path was wanted on CPU but cannot load). ``compiled`` on a non-CPU device or without
    numba is an error; other names pass through."""
    if backend == "auto" and _STATE.get("auto") and device.type == "cpu":
        backend = _STATE["auto"]
    if backend == "auto":
        if device.type != "cpu":
            return "tiles"
        if load() is None:
            if not _STATE.get("warned"):
                warnings.warn(f"compiled CPU backend unavailable ({load_error()}); "
                              "rendering with the torch path (backend=tiles), several times slower",
                              RuntimeWarning, stacklevel=3)
                _STATE["warned"] = True
            return "tiles"
        return "compiled"
    if backend == "compiled":
        if device.type != "cpu":
            raise ValueError(f"backend 'compiled' runs on CPU tensors only, got device {device}")
        if load() is None:
            raise RuntimeError(f"backend 'compiled' cannot load: {load_error()}")
    return backend


def use_threads() -> int:
    """The kernels' thread count: what torch was given, capped at numba's pool. One thread runs
    the kernels serially without touching numba's thread pool at all (``set_num_threads`` would
    start it, and its idle threads spin on the cores other jobs are using). Inside
    ``map_in_threads`` it is 1: the calls there run side by side, each on one thread."""
    threads = torch.get_num_threads()
    if threads <= 1 or getattr(_THREAD, "side_by_side", False):
        return 1
    import numba
    threads = max(1, min(threads, numba.config.NUMBA_NUM_THREADS))  # type: ignore[attr-defined]
    numba.set_num_threads(threads)
    return threads


def map_in_threads(fn: Callable[[int], T], count: int, workers: int) -> Iterator[T]:
    """``fn(0), ..., fn(count - 1)``, yielded in that order, computed on ``workers`` threads.

    For independent per-view work whose kernels release the GIL (``nogil``): within ``fn`` the
    kernels run on one thread (``use_threads()`` is 1 there), so the per-view steps that do not
    split over tiles (projection set-up, binning, the depth sort, per-Gaussian sums, the Python
    between them) run side by side too. The results are those of a serial loop: each call
    computes the same thing whatever thread runs it, and the kernels' results do not depend on
    their thread count. Grad mode is per thread: ``fn`` sets its own. At most ``2 * workers``
    calls are in flight, so a long pool is never held in memory beyond what the caller keeps."""
    if workers <= 1 or count <= 1:
        for i in range(count):
            yield fn(i)
        return

    def side_by_side(i: int) -> T:
        _THREAD.side_by_side = True
        return fn(i)

    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="gopre-view") as pool:
        pending = deque(pool.submit(side_by_side, i) for i in range(min(count, 2 * workers)))
        submitted = len(pending)
        while pending:
            result = pending.popleft().result()
            if submitted < count:
                pending.append(pool.submit(side_by_side, submitted))
                submitted += 1
            yield result


def intrinsics(K: Tensor) -> np.ndarray:
    """(fx, fy, cx, cy) float64 of a [3, 3] pinhole matrix, as the kernels take them."""
    return np.array([float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])])


def to_numpy(x: Tensor) -> np.ndarray:
    """A contiguous NumPy view (or copy) of a CPU tensor, detached."""
    return x.detach().contiguous().numpy()


def _array(x) -> np.ndarray:
    return x if isinstance(x, np.ndarray) else to_numpy(x)


class CompiledBins:
    """Depth-sorted per-tile lists built by the compiled counting sort (NumPy arrays), with the
    packed per-Gaussian rows the kernels read. Built from CPU tensors or NumPy arrays.

    gauss_ids [I], offsets [T], counts [T] (same meaning as ``rasterize.TileBins``);
    packed [N, PACKED] float64 (see ``kernels``; rows of Gaussians no tile lists are zeros).
    Packing runs on ``workers`` threads; only the Gaussians some tile lists are depth-sorted.
    """

    def __init__(self, means2d: Tensor, conics: Tensor, opacities: Tensor, radii: Tensor,
                 depths: Tensor, width: int, height: int, tile_size: int, workers: int = 1):
        kernels = load()
        self.width, self.height, self.tile_size = width, height, tile_size
        self.tiles_x, self.tiles_y = -(-width // tile_size), -(-height // tile_size)
        self.packed, rects = kernels.pack_rects(
            _array(means2d), _array(conics), _array(opacities), _array(radii).astype(np.int64),
            self.tiles_x, self.tiles_y, tile_size, workers)
        ids = kernels.listed(rects)
        order = ids[kernels.depth_order(_array(depths)[ids])]  # stable: as the full order, cut
        self.gauss_ids, self.offsets, self.counts = kernels.bin_tiles(rects, order, self.tiles_x,
                                                                      self.tiles_y)

    def forward(self, features: np.ndarray, workers: int):
        """(image [H, W, D] in the features' dtype, final transmittance [H, W] float64,
        walked [H, W] int64)."""
        return load().composite_forward(self.gauss_ids, self.offsets, self.counts, self.packed,
                                        features, self.width, self.height, self.tiles_x,
                                        self.tile_size, workers)

    def walked_rows(self, walked: np.ndarray):
        """(row_start [T], row_ids [R]): one row per intersection some pixel walked."""
        return load().walked_rows(walked, self.offsets, self.gauss_ids, self.tiles_x,
                                  self.tile_size)


class _CompiledComposite(torch.autograd.Function):
    """Compositing by the compiled kernels; the backward sums the per-intersection gradient rows
    into per-Gaussian gradients in row order (``kernels.sum_rows``: deterministic)."""

    @staticmethod
    def forward(ctx, means2d, conics, opacities, features, bins):
        feats = to_numpy(features)
        image, final, walked = bins.forward(feats, use_threads())
        ctx.bins, ctx.feats, ctx.final, ctx.walked = bins, feats, final, walked
        ctx.n = means2d.shape[0]
        return torch.from_numpy(image), torch.from_numpy(final).to(features.dtype)

    @staticmethod
    def backward(ctx, grad_image, grad_final):
        bins = ctx.bins
        row_start, row_ids = bins.walked_rows(ctx.walked)
        rows = load().composite_backward(
            bins.gauss_ids, bins.offsets, row_start, row_ids.shape[0], bins.packed, ctx.feats,
            ctx.final, ctx.walked, to_numpy(grad_image.double()), to_numpy(grad_final.double()),
            bins.tiles_x, bins.tile_size, use_threads())
        per_gauss = torch.from_numpy(load().sum_rows(row_ids, rows, ctx.n, ctx.feats))
        return per_gauss[:, 0:2], per_gauss[:, 2:5], per_gauss[:, 5], per_gauss[:, 6:], None


def rasterize_compiled(means2d: Tensor, conics: Tensor, opacities: Tensor, features: Tensor,
                       radii: Tensor, depths: Tensor, width: int, height: int,
                       tile_size: int = 8) -> tuple[Tensor, Tensor]:
    """Same contract as ``rasterize.rasterize``: (features image [H, W, D], alpha [H, W]).

    CPU tensors only; float32 or float64 (all inputs in one dtype).
    """
    if load() is None:
        raise RuntimeError(f"backend 'compiled' cannot load: {load_error()}")
    bins = CompiledBins(means2d, conics, opacities, radii, depths, width, height, tile_size,
                        use_threads())
    image, final = _CompiledComposite.apply(means2d, conics, opacities, features, bins)
    return image, 1 - final


def projection_kernels():
    """The projection kernels module (loaded on first use, like the compositing kernels)."""
    from pipeline.splat import project_kernels
    return project_kernels


def kernel_camera(viewmat: Tensor, K: Tensor, width: int, height: int, sh_degree: int,
                  near: float) -> tuple:
    """The camera arguments the projection kernels take: (view [4, 4] float64, intrinsics,
    width, height, SH degree, near)."""
    view = viewmat.detach().double().contiguous().numpy()
    return view, intrinsics(K), int(width), int(height), int(sh_degree), float(near)


class _CompiledProjection(torch.autograd.Function):
    """``project`` by the compiled kernels, with the hand-written backward to the raw parameters
    (no gradient to the camera)."""

    @staticmethod
    def forward(ctx, means, log_scales, quats, logit_opacities, sh0, shN, camera):
        arrays = tuple(to_numpy(x) for x in (means, log_scales, quats, logit_opacities, sh0, shN))
        workers = use_threads()
        outs = projection_kernels().project_forward(*arrays, *camera, workers)
        ctx.arrays, ctx.camera, ctx.workers = arrays, camera, workers
        dtype = means.dtype
        means2d, conics, depths, radii, colors, opacities = (torch.from_numpy(x) for x in outs)
        ctx.mark_non_differentiable(radii)
        return (means2d.to(dtype), conics.to(dtype), depths.to(dtype), radii, colors.to(dtype),
                opacities.to(dtype))

    @staticmethod
    def backward(ctx, g_means2d, g_conics, g_depths, _g_radii, g_colors, g_opacities):
        grads = projection_kernels().project_backward(
            *ctx.arrays, *ctx.camera,
            *(to_numpy(x.double()) for x in (g_means2d, g_conics, g_depths, g_colors, g_opacities)),
            ctx.workers)
        dtype = g_means2d.dtype
        return (*(torch.from_numpy(x).to(dtype) for x in grads), None)


def project_compiled(gaussians, viewmat: Tensor, K: Tensor, width: int, height: int,
                     sh_degree: int | None = None, near: float = 0.01):
    """Same contract as ``project.project`` (a ``Projection``), by the compiled kernels.

    Differentiable w.r.t. the Gaussians' raw parameters (not the camera); CPU tensors only.
    """
    from pipeline.splat.project import Projection, active_sh_degree
    sh_degree = active_sh_degree(gaussians, sh_degree)
    camera = kernel_camera(viewmat, K, width, height, sh_degree, near)
    means2d, conics, depths, radii, colors, opacities = _CompiledProjection.apply(
        gaussians.means, gaussians.log_scales, gaussians.quats, gaussians.logit_opacities,
        gaussians.sh0, gaussians.shN, camera)
    return Projection(means2d, conics, depths, radii, colors, opacities)


def project_visible_arrays(arrays: tuple, camera: tuple, workers: int) -> tuple:
    """``project_forward`` of the raw parameters as NumPy ``arrays`` (means, log_scales, quats,
    logit_opacities, sh0, shN) for ``camera`` (``kernel_camera``) with the colour and conic of
    visible Gaussians only (``all_colors`` False: a culled one's are 0, and no tile lists it):
    (means2d, conics, depths, radii, colors, opacities), in the parameters' dtype as
    ``project_compiled`` casts them (the kernel writes them in it already, so no copy)."""
    np_dtype = arrays[0].dtype
    outs = projection_kernels().project_forward(*arrays, *camera, workers, False)
    return tuple(x if x.dtype == np.int64 else x.astype(np_dtype, copy=False) for x in outs)


def project_visible(arrays: tuple, viewmat: Tensor, K: Tensor, width: int, height: int,
                    sh_degree: int, near: float, workers: int):
    """``project_compiled``'s values without autograd (``project_visible_arrays``) as a
    ``Projection``; culled Gaussians (radius 0) have colour and conic 0."""
    from pipeline.splat.project import Projection
    camera = kernel_camera(viewmat, K, width, height, sh_degree, near)
    return Projection(*(torch.from_numpy(x) for x in project_visible_arrays(arrays, camera, workers)))
