import json
import os
import re
import resource
import socket
import time
from pathlib import Path

import pytest
import torch

SHARED_DATA = Path(os.environ.get("GOPRE_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))


def share_of_cores() -> int:
    """Threads per test process: the machine's cores shared among pytest-xdist's workers (`make test`:
    2 workers on 2 cores, one thread each; one process alone: 2). A process given more threads than its
    share makes torch's threads wait on each other: the acquisition and Fisher tests on 2 workers took
    291 s at 2 threads each and 53 s at 1 (2026-12-07, beside a sweep)."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    return max(1, min(2, cores // workers))


# `make mutate` sets 1, since mutmut forks its workers from a process that must never have entered a
# parallel OpenMP region (fork-unsafe).
TEST_THREADS = int(os.environ.get("GOPRE_TEST_THREADS", share_of_cores()))
# The processes the tests start (gopre-run, `ray start` nodes, servers) get the same share: torch's
# default, a thread per core, beside the other worker costs a tiny scene's ray casting 12x its
# one-thread time (0.43 against 0.037 s a 32 px view, 2026-12-07, beside a 2-job sweep). A value
# set by hand is kept; one this file set (pytest-xdist's controller, whose share is the whole machine,
# before it starts the workers, which inherit its environment) is each worker's own share.
_SET_BY_CONFTEST = "GOPRE_TEST_SET_THREAD_VARS"  # the names this file set, comma-separated
_ours = set(filter(None, os.environ.get(_SET_BY_CONFTEST, "").split(",")))
for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    if _var not in os.environ or _var in _ours:
        os.environ[_var] = str(TEST_THREADS)
        _ours.add(_var)
os.environ[_SET_BY_CONFTEST] = ",".join(sorted(_ours))


@pytest.fixture(autouse=True)
def _threads(request):
    """The process's share of the cores; a test marked ``threads(n)`` gets n (the compiled kernels'
    threaded branches against their oracles run threaded whatever the share), unless
    ``GOPRE_TEST_THREADS`` is set."""
    marker = request.node.get_closest_marker("threads")
    pinned = "GOPRE_TEST_THREADS" in os.environ  # set by hand (make mutate: 1): it holds for every test
    torch.set_num_threads(marker.args[0] if marker is not None and not pinned else TEST_THREADS)
    yield


@pytest.fixture(scope="session", autouse=True)
def _scene_cache(tmp_path_factory):
    """One cache of generated scenes for the whole run (``GOPRE_SCENE_CACHE``), shared by pytest-xdist's
    workers and the processes the tests start: each tiny scene is ray-cast once, not in every test that
    runs a sweep (8 s each). A cache already set by hand is kept; a test of the uncached path unsets it."""
    from pipeline.data.generated_cache import CACHE_ENV
    root = tmp_path_factory.getbasetemp()
    run_root = root.parent if os.environ.get("PYTEST_XDIST_WORKER") else root  # pytest-N: this run's
    os.environ.setdefault(CACHE_ENV, str(run_root / "scene_cache"))
    yield


@pytest.fixture(scope="module")
def ray_session():
    """A local Ray instance of 2 CPUs for the module's tests (Ray's own, started and stopped here)."""
    ray = pytest.importorskip("ray")
    ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield ray
    ray.shutdown()


# The generated scene at the size the sweep tests need (the dataset's default, 100 px with 100 + 200
# views, is 27 M rays to cast: about 100 CPU seconds, where this one takes about 1).
SMALL_GENERATED = ["dataset.generated.generate.size=32", "dataset.generated.generate.n_train=16",
                   "dataset.generated.generate.n_test=8"]


def shared_scene(*parts: str) -> Path:
    """Path to a staged scene under ../shared/data, or skip the test with the reason."""
    path = SHARED_DATA.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"staged data not found at {path} (set GOPRE_SHARED_DATA or place ../shared/data)")
    return path


def free_port() -> int:
    """A TCP port nobody listens on right now (for servers the tests start)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# `make test` runs the suite in pytest-xdist processes, one per core. Two kinds of test run one after
# another, each kind in one process: those that start Ray (a sweep's local Ray, `ray start` nodes, the
# driver subprocesses they kill: Ray's default node ports, such as its dashboard agent's, are the
# machine's, and two Ray sweeps at once on two cores miss each other's timings), and those that start
# servers of their own (PostgreSQL, MLflow servers). The two chains share nothing, so they may run
# beside each other. The chain is a function of the test's id, and a scheduler of ours sends each
# chain to one process as one unit: pytest-xdist's own `loadgroup` reads a group from a suffix it
# writes into the test's id, which pytest 9.2 no longer takes (pytest-xdist issue 1386), so until
# 2026-12-08 the "chain" was silently spread over both processes (33 and 34 tests); two Ray sweeps
# at once then lost a round's progress, or printed a job's round after the job had ended (CI,
# 2026-12-07). tests/test_test_costs.py runs a small suite on two processes and checks the chains.
RAY_MODULES = {"test_ray_cluster", "test_interrupt", "test_executors"}
SERVER_MODULES = {"test_tracking_server", "test_shared_tracking"}


def chain_of(nodeid: str) -> str | None:
    """The chain a test runs in, from its id: "ray" (its module starts Ray, or its name or parameters
    say ray, or it runs ``executor=ray``), "servers", or None for a test that runs anywhere."""
    path, _, rest = nodeid.partition("::")
    module = Path(path).stem
    name, _, params = rest.partition("[")
    words = set(name.split("_")) | set(re.split(r"[^A-Za-z0-9]+", params))
    if module in RAY_MODULES or "executor=ray" in nodeid or "ray" in words:
        return "ray"
    if module in SERVER_MODULES:
        return "servers"
    return None


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config: pytest.Config, log):
    """With ``--dist loadgroup``: each chain one unit of work (one process, its tests in order), every
    other test a unit of its own."""
    if config.getvalue("dist") != "loadgroup":
        return None
    from xdist.scheduler import LoadScopeScheduling

    class ChainScheduling(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return chain_of(nodeid) or nodeid
    return ChainScheduling(config, log)


# Where the suite's time goes, measured so that a loaded machine does not hide it:
# GOPRE_TEST_RESOURCES=path appends one JSON line per test (setup, call and teardown together): its
# wall seconds, the CPU seconds of its process and of the processes it started and reaped (a sweep's
# driver, servers; a process left running, such as a Ray node's workers killed with it, is not
# counted), its xdist worker and the chain it ran in. ``python tools/test_costs.py
# path`` sums them. CPU seconds hardly depend on the load beside the run; wall seconds do.
RESOURCE_LOG = os.environ.get("GOPRE_TEST_RESOURCES", "").strip()


def _cpu_seconds() -> tuple[float, float]:
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime, children.ru_utime + children.ru_stime


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None):
    if not RESOURCE_LOG:
        yield
        return
    own, children = _cpu_seconds()
    start = time.perf_counter()
    yield
    wall = time.perf_counter() - start
    own_after, children_after = _cpu_seconds()
    line = {"test": item.nodeid, "wall_s": round(wall, 3), "cpu_s": round(own_after - own, 3),
            "children_cpu_s": round(children_after - children, 3),
            "worker": os.environ.get("PYTEST_XDIST_WORKER", "main"), "chain": chain_of(item.nodeid)}
    with open(RESOURCE_LOG, "a") as log:  # one short line per write: the workers' lines do not interleave
        log.write(json.dumps(line) + "\n")
