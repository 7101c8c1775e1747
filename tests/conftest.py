import os
import socket
from pathlib import Path

import pytest
import torch

SHARED_DATA = Path(os.environ.get("GOPRE_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))


# Threads per test process: 2 (the machine's cores); `make mutate` sets 1, since mutmut forks its
# workers from a process that must never have entered a parallel OpenMP region (fork-unsafe).
TEST_THREADS = int(os.environ.get("GOPRE_TEST_THREADS", "2"))


@pytest.fixture(autouse=True)
def _threads():
    torch.set_num_threads(TEST_THREADS)
    yield


@pytest.fixture(scope="module")
def ray_session():
    """A local Ray instance of 2 CPUs for the module's tests (Ray's own, started and stopped here)."""
    ray = pytest.importorskip("ray")
    ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield ray
    ray.shutdown()


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


# `make test` runs the suite in two processes (pytest-xdist, --dist loadgroup). The tests that start
# clusters and servers (Ray, `ray start` nodes, PostgreSQL and MLflow servers, the driver subprocesses
# they kill) run one after another in one process: Ray finds "the latest cluster on this machine", the
# servers' ports and processes are the machine's, and two such tests side by side would see each other.
CLUSTER_MODULES = {"test_ray_cluster", "test_interrupt", "test_tracking_server", "test_shared_tracking",
                   "test_executors", "test_deploy"}


def _starts_a_cluster(item: pytest.Item) -> bool:
    module = item.module.__name__.rsplit(".", 1)[-1] if item.module else ""
    if module in CLUSTER_MODULES or "ray_session" in getattr(item, "fixturenames", ()):
        return True
    return "executor=ray" in item.nodeid or "ray" in item.name.split("[")[0].split("_")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        if _starts_a_cluster(item):
            item.add_marker(pytest.mark.xdist_group("cluster"))
