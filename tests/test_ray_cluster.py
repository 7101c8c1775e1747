"""What the docker compose cluster runs, started directly: `ray start --head` and a sweep that
joins it with `executor.address` (the driver in its own process, as on the head container)."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import free_port

BIN = Path(sys.executable).parent


@pytest.mark.slow
def test_a_sweep_joins_a_running_ray_cluster(tmp_path):
    ray_bin = BIN / "ray"
    if not ray_bin.exists():
        pytest.skip("the ray command is not installed in this environment")
    port = free_port()
    head = subprocess.Popen([str(ray_bin), "start", "--head", f"--port={port}", "--num-cpus=2",
                             "--include-dashboard=false", "--block"], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, start_new_session=True)
    try:
        out = tmp_path / "cluster"
        # `auto` = the cluster this machine started last (the head binds the node's IP, not 127.0.0.1)
        cmd = [str(BIN / "pipeline-run"), "experiment=debug", "executor=ray", "executor.address=auto",
               "method=[random,coverage]", "splat.iterations=100", "protocol.budget=3", f"output_dir={out}",
               "dataset.generated.generate.n_train=12", "dataset.generated.generate.n_test=6"]
        for line in head.stdout:  # wait until the head is up
            if "Ray runtime started" in line:
                break
        assert head.poll() is None, "ray head did not come up"
        result = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
        assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-2000:]
        summary = json.loads((out / "summary.json").read_text())
        assert summary["finished"] == 2 and summary["failed"] == 0
        assert "Connected to Ray cluster" in result.stdout + result.stderr  # joined, did not start one
    finally:
        os.killpg(head.pid, 15)
        head.wait(timeout=60)
