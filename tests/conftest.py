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
