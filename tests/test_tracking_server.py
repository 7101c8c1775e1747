"""A real MLflow tracking server on a real PostgreSQL (the recipe of docker/compose.yaml), with
proxied artifacts: what a sweep logs is seen by a client that does not share the driver's disk, an
outage mid-round is replayed, and nothing is left RUNNING. PostgreSQL comes from the system
packages (`make postgres`); without it these tests skip with the reason."""

import glob
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

import pytest

from pipeline.experiment.layout import SweepFolder
from tests.conftest import free_port
from tests.test_experiment import TINY

BIN = Path(sys.executable).parent
pytestmark = pytest.mark.slow


def postgres_bin(name: str) -> str | None:
    found = shutil.which(name) or next(iter(sorted(glob.glob(f"/usr/lib/postgresql/*/bin/{name}"))), None)
    return found


def as_postgres(cmd: list[str]) -> list[str]:
    """PostgreSQL refuses to run as root: run its commands as the postgres user when we are root."""
    if os.geteuid() != 0:
        return cmd
    return ["runuser", "-u", "postgres", "--", *cmd]


@pytest.fixture(scope="module")
def postgres():
    initdb, pg_ctl = postgres_bin("initdb"), postgres_bin("pg_ctl")
    if initdb is None or pg_ctl is None:
        pytest.skip("PostgreSQL is not installed (make postgres installs Debian's package)")
    pytest.importorskip("psycopg", reason="the server extra is not installed: pip install 'gopre[server]'")
    root = Path(tempfile.mkdtemp(prefix="gopre-pg-"))  # not under pytest's 0700 folder: postgres reads it
    if os.geteuid() == 0:
        shutil.chown(root, "postgres")
    data, port = root / "data", free_port()
    subprocess.run(as_postgres([initdb, "-D", str(data), "-U", "mlflow", "--auth=trust"]), check=True,
                   capture_output=True, timeout=120)
    subprocess.run(as_postgres([pg_ctl, "-D", str(data), "-l", str(root / "log"), "-w", "start", "-o",
                                f"-p {port} -k {root} -c listen_addresses=127.0.0.1"]),
                   check=True, capture_output=True, timeout=120)
    try:
        yield f"postgresql://mlflow@127.0.0.1:{port}/postgres"
    finally:
        subprocess.run(as_postgres([pg_ctl, "-D", str(data), "-m", "immediate", "stop"]), capture_output=True,
                       timeout=120)
        shutil.rmtree(root, ignore_errors=True)


class Server:
    """``mlflow server`` on the PostgreSQL store with proxied artifacts (its own process group)."""

    def __init__(self, store: str, artifacts: Path, port: int, log: Path):
        self.cmd = [str(BIN / "mlflow"), "server", "--backend-store-uri", store, "--artifacts-destination",
                    str(artifacts), "--host", "127.0.0.1", "--port", str(port), "--workers", "1"]
        self.url, self.log, self.proc = f"http://127.0.0.1:{port}", log, None

    def start(self) -> "Server":
        self.proc = subprocess.Popen(self.cmd, stdout=open(self.log, "ab"), stderr=subprocess.STDOUT,
                                     start_new_session=True)
        deadline = time.time() + 120
        while time.time() < deadline:
            assert self.proc.poll() is None, self.log.read_text()[-3000:]
            try:
                urllib.request.urlopen(self.url + "/health", timeout=2).close()
                return self
            except OSError:
                time.sleep(0.5)
        raise AssertionError("mlflow server did not come up:\n" + self.log.read_text()[-3000:])

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            os.killpg(self.proc.pid, 9)
            self.proc.wait(timeout=60)


@pytest.fixture()
def server(postgres, tmp_path):
    artifacts = tmp_path / "server_artifacts"  # the server's disk; the driver never writes here
    srv = Server(postgres, artifacts, free_port(), tmp_path / "server.log").start()
    srv.artifacts = artifacts
    yield srv
    srv.stop()


def run(*args, timeout=600):
    return subprocess.run([str(BIN / "gopre-run"), *args], capture_output=True, text=True, timeout=timeout)


def test_a_sweep_on_postgres_is_seen_whole_by_another_client(server, tmp_path):
    from mlflow import MlflowClient
    out = tmp_path / "driver"
    proc = run("experiment=debug", *TINY, "method=[random,coverage]", "executor=local", "tracking=mlflow",
               f"tracking.uri={server.url}", f"output_dir={out}")
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert "a path each client writes itself" not in proc.stdout + proc.stderr  # proxied: no warning
    client = MlflowClient(server.url)  # another client: it shares nothing with the driver but the URL
    experiment = client.get_experiment_by_name("debug")
    assert experiment.artifact_location.startswith("mlflow-artifacts:")
    runs = client.search_runs([experiment.experiment_id], "tags.config_hash != ''")
    assert len(runs) == 2 and all(r.info.status == "FINISHED" for r in runs)
    for r in runs:
        assert r.data.params["protocol.budget"] == "3"
        assert sorted(m.step for m in client.get_metric_history(r.info.run_id, "test_psnr")) == [2, 3]
        assert r.info.artifact_uri.startswith("mlflow-artifacts:")
        got = Path(client.download_artifacts(r.info.run_id, "benchmark/result.json", str(tmp_path / r.info.run_id)))
        assert got.read_bytes() == (out / "jobs" / r.data.tags["config_hash"] / "artifacts" / "benchmark" /
                                    "result.json").read_bytes()
    assert not (out / "mlartifacts").exists()  # the driver wrote no artifact store of its own
    assert list(server.artifacts.rglob("result.json")), "the artifacts are on the server's disk"
    parents = client.search_runs([experiment.experiment_id], "tags.kind = 'sweep'")
    assert [p.info.status for p in parents] == ["FINISHED"]


def test_an_outage_mid_round_is_replayed_by_the_sweep_itself_and_leaves_nothing_running(server, tmp_path):
    """The server goes down after the job's first round and comes back while the driver, its job
    finished and untracked, waits for it: the sweep ends with the job's run FINISHED (replayed), under
    the sweep's parent run, with every round's metrics, its worker tags and its round images, the
    outage's partial run KILLED, and no command typed after it."""
    import threading

    from mlflow import MlflowClient

    from pipeline.experiment.records import records_from_mlflow
    out = tmp_path / "driver"
    args = ["experiment=debug", "name=outage", *TINY, "protocol.budget=6", "splat.iterations=2400", "method=[random]",
            "executor=local", "tracking=mlflow", f"tracking.uri={server.url}", "tracking.replay_wait_s=120",
            "job.round_images=1", f"output_dir={out}"]
    driver = subprocess.Popen([str(BIN / "gopre-run"), *args], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                              text=True)
    client = MlflowClient(server.url)
    deadline = time.time() + 300
    while time.time() < deadline:  # the job's child run has its first round: the server goes down
        experiment = client.get_experiment_by_name("outage")  # the store is shared with the other test
        children = client.search_runs([experiment.experiment_id], "tags.config_hash != ''") if experiment else []
        if children and client.get_metric_history(children[0].info.run_id, "test_psnr"):
            break
        assert driver.poll() is None, driver.stdout.read()[-3000:]
        time.sleep(0.3)
    server.stop()
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(driver.stdout), daemon=True)
    reader.start()
    deadline = time.time() + 300  # the job ends during the outage; the driver says it waits for the server
    while not any("trying again every" in line for line in lines):
        assert time.time() < deadline and driver.poll() is None, "".join(lines)[-3000:]
        time.sleep(0.3)
    server.start()  # back while the driver waits: nobody types anything
    driver.wait(timeout=600)
    reader.join(timeout=60)
    output = "".join(lines)
    assert driver.returncode == 0, output[-3000:]
    assert "1 run(s) replayed" in output and "tracking_sync" not in output.split("run(s) replayed")[-1], output[-3000:]
    experiment = client.get_experiment_by_name("outage")
    every = client.search_runs([experiment.experiment_id], "")
    assert not [r for r in every if r.info.status == "RUNNING"], [(r.data.tags, r.info.status) for r in every]
    jobs = [r for r in every if r.data.tags.get("config_hash")]
    assert sorted(r.info.status for r in jobs) == ["FINISHED", "KILLED"]  # the replay, the partial run
    (replayed,) = [r for r in jobs if r.info.status == "FINISHED"]
    result = json.loads(SweepFolder(out).job(replayed.data.tags["config_hash"]).result_file.read_text())
    steps = sorted(m.step for m in client.get_metric_history(replayed.info.run_id, "test_psnr"))
    assert steps == [r["num_views"] for r in result["rounds"]]  # every round, the outage's too
    (parent,) = [r for r in every if r.data.tags.get("kind") == "sweep"]
    assert replayed.data.tags["mlflow.parentRunId"] == parent.info.run_id and parent.info.status == "FINISHED"
    assert {"worker.host", "worker.code_version", "worker.packages", "worker.cpu"} <= set(replayed.data.tags)
    images = [a.path for a in client.list_artifacts(replayed.info.run_id, "images")]
    saved = SweepFolder(out).job(replayed.data.tags["config_hash"]).saved_round_images()
    for step in saved:  # every round's images, from the job folder
        assert any(f"picked+step+{step}+" in p for p in images), (step, images)
    frame = records_from_mlflow(server.url, "outage")
    final = frame.query("kind == 'final'")
    assert len(final) == 1 and final["status"].tolist() == ["FINISHED"]  # the report reads the replay
    relaunch = run(*args)
    assert relaunch.returncode == 0 and "1 already finished (skipped), 0 to run" in relaunch.stdout + relaunch.stderr
    assert "were not in" not in relaunch.stdout + relaunch.stderr  # nothing left to replay
