"""Real Ray clusters on this machine: `ray start` nodes, each with its own temp dir (and, for a node
that must not see the data, its own mount namespace), and sweeps that join them through
`executor.address` with the driver in its own process, as on a cluster's head."""

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from pipeline.experiment.records import RecordsFile
from tests.conftest import free_port
from tests.test_experiment import TINY, metrics_of

BIN = Path(sys.executable).parent
pytestmark = pytest.mark.slow
TOKEN_ENV = {"RAY_AUTH_MODE": "token"}  # after any local ray.init, `ray start --head` turns token auth on


def ray_bin() -> Path:
    path = BIN / "ray"
    if not path.exists():
        pytest.skip("the ray command is not installed in this environment")
    return path


class RayNode:
    """One `ray start --block` in its own process group (stopped by its group, never by name)."""

    def __init__(self, tmp: Path, name: str, cpus: int, head_port: int | None = None, port: int | None = None,
                 cwd: Path | None = None, hide: Path | None = None, env: dict | None = None):
        temp = Path("/tmp") / f"ray-{name}-{os.getpid()}-{free_port()}"  # short: Ray's socket paths
        self.temp = temp
        args = [str(ray_bin()), "start", f"--num-cpus={cpus}", f"--temp-dir={temp}", "--disable-usage-stats",
                "--block"]
        args += ([f"--address=127.0.0.1:{head_port}"] if head_port else
                 ["--head", f"--port={port}", "--include-dashboard=false"])
        if hide is not None:  # a node that cannot see `hide`: a private tmpfs over it
            args = ["unshare", "-m", "sh", "-c", f'mount -t tmpfs none "{hide}" && exec "$@"', "sh", *args]
        self.log = tmp / f"{name}.log"
        self.proc = subprocess.Popen(args, stdout=open(self.log, "w"), stderr=subprocess.STDOUT,
                                     start_new_session=True, cwd=cwd, env={**os.environ, **TOKEN_ENV, **(env or {})})
        deadline = time.time() + 120
        while "Ray runtime started" not in self.log.read_text():
            assert self.proc.poll() is None and time.time() < deadline, self.log.read_text()[-3000:]
            time.sleep(0.3)

    def kill(self) -> None:
        """The node is lost: every process of it at once (raylet, workers, the head's GCS)."""
        try:
            os.killpg(self.proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        self.proc.wait(timeout=60)

    def owns(self, pid: int) -> bool:
        """``pid`` descends from this node's `ray start` (its raylet's workers do)."""
        for _ in range(20):
            if pid == self.proc.pid:
                return True
            try:
                stat = Path(f"/proc/{pid}/stat").read_text()
            except OSError:
                return False
            pid = int(stat.rsplit(")", 1)[1].split()[1])  # the parent's pid
            if pid <= 1:
                return False
        return False

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.kill()
        shutil.rmtree(self.temp, ignore_errors=True)


@pytest.fixture()
def cluster(tmp_path):
    nodes = []

    def start(*args, **kwargs):
        nodes.append(RayNode(tmp_path, *args, **kwargs))
        return nodes[-1]
    yield start
    for node in reversed(nodes):
        node.stop()


def gopre_run(*args, env=None, **kwargs):
    return subprocess.Popen([str(BIN / "gopre-run"), *args], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, env={**os.environ, **TOKEN_ENV, **(env or {})}, **kwargs)


def test_a_sweep_joins_a_running_ray_cluster(tmp_path, cluster):
    port = free_port()
    cluster("head", 2, port=port)
    out = tmp_path / "cluster"
    driver = gopre_run("experiment=debug", "executor=ray", f"executor.address=127.0.0.1:{port}",
                       "method=[random,coverage]", "splat.iterations=100", "protocol.budget=3", f"output_dir={out}",
                       "dataset.generated.generate.n_train=12", "dataset.generated.generate.n_test=6")
    output, _ = driver.communicate(timeout=600)
    assert driver.returncode == 0, output[-3000:]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["finished"] == 2 and summary["failed"] == 0
    assert "Connected to Ray cluster" in output  # joined, did not start one


def test_losing_a_worker_node_mid_job_loses_nothing(tmp_path, cluster):
    """Two 1-CPU nodes; the worker node, started from another folder, dies mid-job: Ray reruns its
    task on the head, the job resumes from its round checkpoint under output_dir, the sweep
    finishes with the numbers of a local run, and a relaunch skips everything."""
    port = free_port()
    cluster("head", 1, port=port)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    worker = cluster("worker", 1, head_port=port, cwd=elsewhere)
    out = tmp_path / "out"
    common = ["experiment=debug", *TINY, "protocol.budget=6", "splat.iterations=6000", "method=[random,coverage]",
              "job.threads=1", "tracking=mlflow"]
    driver = gopre_run(*common, "executor=ray", f"executor.address=127.0.0.1:{port}", f"output_dir={out}")
    victim, deadline = None, time.time() + 300
    while victim is None:  # a job on the worker node has finished a round: the node is lost
        assert driver.poll() is None and time.time() < deadline, driver.stdout.read()[-3000:]
        for starts in out.glob("jobs/*/starts.jsonl"):
            first = json.loads(starts.read_text().splitlines()[0])
            log = starts.parent / "log.txt"
            if worker.owns(first["pid"]) and log.exists() and "round 0:" in log.read_text():
                victim = starts.parent.name
        time.sleep(0.2)
    worker.kill()
    output, _ = driver.communicate(timeout=900)
    assert driver.returncode == 0, output[-4000:]
    assert "round progress" not in output  # the inbox was on the driver's node, not on the lost one
    frame = RecordsFile(out).frame
    finals = frame.query("kind == 'final'").set_index("config_hash")
    assert (finals["status"] == "FINISHED").all() and len(finals) == 2
    assert finals.loc[victim, "starts"] == 2  # started on the lost node, then again on the head
    assert "resuming from the checkpoint after" in (out / "jobs" / victim / "log.txt").read_text()
    assert not list(elsewhere.iterdir()), "a job wrote its state under the worker's cwd"
    # the lost job, run again uninterrupted in one local process, gives the same numbers (the other
    # job never moved: running it again would test nothing the lost one does not)
    lost_method = finals.loc[victim, "method"]
    local_out = tmp_path / "local"
    local = gopre_run(*[c for c in common if not c.startswith("method=")], f"method=[{lost_method}]",
                      "executor=local", "tracking=none", f"output_dir={local_out}")
    assert local.wait(timeout=900) == 0
    assert metrics_of(frame[frame["config_hash"] == victim]) == metrics_of(RecordsFile(local_out).frame)
    relaunch = gopre_run(*common, "executor=ray", f"executor.address=127.0.0.1:{port}", f"output_dir={out}")
    output, _ = relaunch.communicate(timeout=600)
    assert relaunch.returncode == 0 and "2 already finished (skipped), 0 to run" in output, output[-3000:]
    from mlflow import MlflowClient
    client = MlflowClient(f"sqlite:///{out / 'mlflow.db'}")
    runs = client.search_runs([client.get_experiment_by_name("debug").experiment_id], "")
    assert not [r for r in runs if r.info.status == "RUNNING"]


def test_a_node_without_the_data_and_a_driver_without_the_token_are_one_error_each(tmp_path, cluster):
    port = free_port()
    cluster("head", 1, port=port)
    scenes = tmp_path / "scenes"  # where the debug preset generates its scene (beside output_dir)
    scenes.mkdir()
    cluster("blind", 1, head_port=port, hide=scenes)
    args = ["experiment=debug", *TINY, "method=[random]", "executor=ray", f"executor.address=127.0.0.1:{port}",
            f"output_dir={tmp_path / 'out'}"]
    proc = gopre_run(*args)
    output, _ = proc.communicate(timeout=600)
    assert proc.returncode == 2, output[-3000:]
    problems = [ln for ln in output.splitlines() if "cannot read" in ln]
    assert len(problems) == 1 and "scene file(s)" in problems[0], output[-3000:]  # the blind node, only it
    assert not (tmp_path / "out" / "jobs").exists() or not list((tmp_path / "out" / "jobs").glob("*/starts.jsonl"))
    env = {k: v for k, v in os.environ.items() if k != "RAY_AUTH_MODE"}
    refused = subprocess.run([str(BIN / "gopre-run"), *args], capture_output=True, text=True, timeout=600, env=env)
    assert refused.returncode == 2
    assert "RAY_AUTH_MODE=token" in refused.stderr and "Traceback" not in refused.stderr, refused.stderr[-3000:]


def test_the_cluster_extra_joins_through_ray_client_and_the_jobs_api(tmp_path, cluster):
    """gopre[cluster]: Ray Client (executor.address=ray://...) and the dashboard's Jobs API
    (`ray job submit`, what KubeRay's RayJob uses) on a head started as docker/compose.yaml does."""
    pytest.importorskip("grpc", reason="the cluster extra is not installed: pip install 'gopre[cluster]'")
    port, client_port, dashboard_port = free_port(), free_port(), free_port()
    head = RayNode.__new__(RayNode)  # a head with the dashboard and the Ray Client server
    temp = Path("/tmp") / f"ray-dash-{os.getpid()}-{port}"
    head.temp, head.log = temp, tmp_path / "head.log"
    head.proc = subprocess.Popen(
        [str(ray_bin()), "start", "--head", f"--port={port}", "--num-cpus=2", f"--temp-dir={temp}",
         "--disable-usage-stats", "--include-dashboard=true", "--dashboard-host=127.0.0.1",
         f"--dashboard-port={dashboard_port}", f"--ray-client-server-port={client_port}",
         # the agent's default ports are fixed: another Ray on this machine (a sweep running beside
         # the tests) holds them, and the head's job agent would never come up
         f"--dashboard-agent-listen-port={free_port()}", f"--dashboard-agent-grpc-port={free_port()}",
         f"--runtime-env-agent-port={free_port()}", f"--metrics-export-port={free_port()}", "--block"],
        stdout=open(head.log, "w"), stderr=subprocess.STDOUT, start_new_session=True,
        env={**os.environ, **TOKEN_ENV})
    try:
        deadline = time.time() + 180
        while "Ray runtime started" not in head.log.read_text():
            assert head.proc.poll() is None and time.time() < deadline, head.log.read_text()[-3000:]
            time.sleep(0.3)
        common = ["experiment=debug", *TINY, "method=[random]", "tracking=none", "executor=ray"]
        for _ in range(10):  # the Ray Client server answers some seconds after the runtime (more when loaded)
            through_client = gopre_run(*common, f"executor.address=ray://127.0.0.1:{client_port}",
                                       f"output_dir={tmp_path / 'client'}")
            output, _ = through_client.communicate(timeout=600)
            if "no Ray cluster answers" not in output and "not be serving yet" not in output:
                break
            time.sleep(5)
        assert through_client.returncode == 0, output[-3000:]
        assert json.loads((tmp_path / "client" / "summary.json").read_text())["finished"] == 1
        for _ in range(20):  # the head's job agent comes up after its dashboard (slower on a loaded machine)
            submitted = subprocess.run(
                [str(ray_bin()), "job", "submit", "--address", f"http://127.0.0.1:{dashboard_port}", "--",
                 str(BIN / "gopre-run"), *common, "executor.address=auto", f"output_dir={tmp_path / 'job'}"],
                capture_output=True, text=True, timeout=600, env={**os.environ, **TOKEN_ENV})
            if "No available agent to submit job" not in submitted.stdout + submitted.stderr:
                break
            time.sleep(5)
        assert submitted.returncode == 0, submitted.stdout[-3000:] + submitted.stderr[-3000:]
        assert "succeeded" in submitted.stdout + submitted.stderr
        assert json.loads((tmp_path / "job" / "summary.json").read_text())["finished"] == 1
    finally:
        head.stop()
