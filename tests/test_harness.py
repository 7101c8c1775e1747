"""The suite's own harness (tests/conftest.py): the processes a test starts run on that test
process's share of the cores."""

import os
import subprocess
import sys

import pytest

from tests.conftest import TEST_THREADS


def test_a_process_a_test_starts_gets_this_workers_share_of_the_cores():
    """Under pytest-xdist the workers inherit the controller's environment, whose share is the whole
    machine: a started process must still get this worker's share (the first version did not)."""
    if "OMP_NUM_THREADS" not in os.environ.get("GOPRE_TEST_SET_THREAD_VARS", "").split(","):
        pytest.skip("OMP_NUM_THREADS was set by hand for this run")
    child = subprocess.run([sys.executable, "-c", "import torch; print(torch.get_num_threads())"],
                           capture_output=True, text=True, timeout=300)
    assert child.returncode == 0, child.stderr[-2000:]
    assert int(child.stdout.strip()) == TEST_THREADS

