"""The deployment files, read as their tools read them (no Docker engine or Kubernetes runs here;
what the containers run is exercised directly by tests/test_ray_cluster.py and
tests/test_tracking_server.py): docker compose, and KubeRay's RayJob."""

import shlex
from pathlib import Path

import yaml

from pipeline.experiment.provenance import PACKAGE_ROOT, read_lock
from tests.test_experiment import composed

DOCKER = PACKAGE_ROOT / "docker"
RAYJOB = PACKAGE_ROOT / "deploy" / "kuberay" / "rayjob.yaml"


def gopre_overrides(command: str) -> list[str]:
    """The Hydra overrides of a `gopre-run ...` command line."""
    words = shlex.split(command)
    assert words[0] == "gopre-run", command
    return words[1:]


def test_the_compose_tracking_server_is_postgres_with_proxied_artifacts():
    compose = yaml.safe_load((DOCKER / "compose.yaml").read_text())
    mlflow = compose["services"]["mlflow"]["command"]
    assert "--backend-store-uri postgresql://" in mlflow  # psycopg 3 (the server extra, locked)
    assert "--artifacts-destination" in mlflow and "--default-artifact-root" not in mlflow
    assert "psycopg" in read_lock() and "psycopg-binary" in read_lock()


def test_the_compose_cluster_serves_every_port_it_publishes_and_shares_output_dir():
    compose = yaml.safe_load((DOCKER / "compose.yaml").read_text())
    head = compose["services"]["ray-head"]
    published = {int(p.split(":")[0]) for p in head["ports"]}
    assert published == {6379, 8265, 10001}
    assert "--dashboard-host=0.0.0.0" in head["command"] and "--ray-client-server-port=10001" in head["command"]
    lock = read_lock()
    assert {"aiohttp-cors", "grpcio", "opencensus"} <= set(lock)  # ray[default] (dashboard), ray[client]
    for name in ("ray-head", "ray-worker"):  # the nodes (the driver runs on the head)
        service = compose["services"][name]
        assert "outputs:/app/outputs" in service.get("volumes", compose["x-gopre"]["volumes"])
        assert service["environment"]["RAY_AUTH_MODE"] == "token"
    assert compose["services"]["mlflow"]["volumes"] == ["mlartifacts:/mlartifacts"]  # the server's own disk
    worker = yaml.safe_load((DOCKER / "compose.worker.yaml").read_text())["services"]["ray-worker"]
    assert worker["command"].startswith("ray start --address=") and worker["environment"]["RAY_AUTH_MODE"] == "token"
    assert any(v.endswith(":/app/outputs") for v in worker["volumes"])


def test_the_kuberay_rayjob_has_what_kuberay_requires_and_a_valid_sweep(tmp_path):
    job = yaml.safe_load(RAYJOB.read_text())
    assert job["apiVersion"] == "ray.io/v1" and job["kind"] == "RayJob" and job["metadata"]["name"]
    spec = job["spec"]
    cluster = spec["rayClusterSpec"]
    assert cluster["rayVersion"] == read_lock()["ray"]  # the image's Ray
    pods = [cluster["headGroupSpec"]] + cluster["workerGroupSpecs"]
    for pod in pods:
        assert all(isinstance(v, str) for v in pod["rayStartParams"].values())  # KubeRay wants strings
        (container,) = pod["template"]["spec"]["containers"]
        assert container["image"] and container["name"]
        mounts = {m["name"]: m["mountPath"] for m in container["volumeMounts"]}
        assert mounts["outputs"] == "/app/outputs" and mounts["data"] == "/data"
        claims = {v["name"]: v for v in pod["template"]["spec"]["volumes"]}
        assert "persistentVolumeClaim" in claims["outputs"]  # one ReadWriteMany volume every pod shares
    for group in cluster["workerGroupSpecs"]:
        assert group["groupName"] and group["minReplicas"] <= group["replicas"] <= group["maxReplicas"]
    overrides = gopre_overrides(spec["entrypoint"])
    assert "executor=ray" in overrides and "executor.address=auto" in overrides
    output_dir = next(o.split("=", 1)[1] for o in overrides if o.startswith("output_dir="))
    assert Path(output_dir).is_relative_to("/app/outputs")  # on the shared volume
    cfg = composed(overrides)  # the sweep it launches composes (a wrong key fails here)
    assert cfg.executor.kind == "ray" and cfg.name == "table1_global"
