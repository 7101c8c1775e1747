"""tools/test_costs.py and the per-test resource lines tests/conftest.py writes: the suite's floor is
the longer of its CPU spread over the cores and the cluster chain's wall time; the costliest test is
ranked by its own and its children's CPU."""

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
spec = importlib.util.spec_from_file_location("test_costs", ROOT / "tools" / "test_costs.py")
costs = importlib.util.module_from_spec(spec)
sys.modules["test_costs"] = costs  # its dataclass looks its module up
spec.loader.exec_module(costs)


def _line(test, wall, own, children, cluster=False, chain=None):
    line = {"test": test, "wall_s": wall, "cpu_s": own, "children_cpu_s": children, "worker": "gw0", "cluster": cluster}
    if chain is not None:
        line["chain"] = chain
    return json.dumps(line)


def test_the_floor_is_the_cpu_spread_or_the_chain_whichever_is_longer(tmp_path):
    log = tmp_path / "c.jsonl"
    log.write_text("\n".join([_line("a.py::x", 10, 100, 20), _line("b.py::y", 50, 1, 1, cluster=True),
                              _line("b.py::z", 5, 30, 0)]) + "\n")
    text = costs.summary(costs.read_costs(log), top=2, cores=2)
    assert "3 tests, 152 CPU s" in text
    assert "the suite's floor on 2 cores: 1.3 min" in text  # 152 / 2 = 76 s > the chain's 50 s
    assert costs.summary(costs.read_costs(log), top=2, cores=4).count("floor on 4 cores: 0.8 min") == 1  # the chain
    ranked = text.split("costliest 2 tests")[1].splitlines()[1:3]
    assert "a.py::x" in ranked[0] and "b.py::z" in ranked[1]  # 120 (own + children) before 30


def test_the_suite_writes_one_line_per_test_with_its_childrens_cpu(tmp_path):
    """A test that spends CPU in a child process has it in children_cpu_s, not in its own."""
    (tmp_path / "test_spin.py").write_text(
        "import subprocess, sys\n"
        "def test_child():\n"
        "    subprocess.run([sys.executable, '-c', 'sum(range(30_000_000))'], check=True)\n"
        "def test_nothing():\n"
        "    pass\n")
    (tmp_path / "conftest.py").write_text((ROOT / "tests" / "conftest.py").read_text())
    log = tmp_path / "costs.jsonl"
    env = {"GOPRE_TEST_RESOURCES": str(log), "PATH": "/usr/bin:/bin", "PYTHONPATH": str(ROOT)}
    subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-n", "0", str(tmp_path)],
                   check=True, env=env, cwd=tmp_path, capture_output=True)
    lines = {c.test.split("::")[1]: c for c in costs.read_costs(log)}
    assert set(lines) == {"test_child", "test_nothing"}
    assert lines["test_child"].children_cpu_s > 0.2 > lines["test_nothing"].children_cpu_s


def test_the_floor_is_the_longest_of_two_chains_and_an_old_log_reads_as_one(tmp_path):
    """Two chains run beside each other: the floor is the longer one, not their sum; a log written
    before the chains had names counts its flagged tests as one chain, "cluster"."""
    log = tmp_path / "c.jsonl"
    log.write_text("\n".join([_line("r.py::a", 40, 1, 1, True, "ray"), _line("r.py::b", 30, 1, 1, True, "ray"),
                              _line("s.py::c", 50, 1, 1, True, "servers"), _line("x.py::d", 1, 2, 0)]) + "\n")
    text = costs.summary(costs.read_costs(log), top=4, cores=2)
    assert "ray chain: 2 tests, 70 wall s" in text and "servers chain: 1 tests, 50 wall s" in text
    assert "floor on 2 cores: 1.2 min" in text  # the ray chain's 70 s, not 120
    assert "[servers]" in text and "[ray]" in text
    old = tmp_path / "old.jsonl"
    old.write_text(_line("r.py::a", 40, 1, 1, True) + "\n" + _line("x.py::d", 1, 2, 0) + "\n")
    assert "cluster chain: 1 tests, 40 wall s" in costs.summary(costs.read_costs(old), top=2, cores=2)


def test_each_chain_runs_in_one_process_of_two(tmp_path):
    """`make test`'s scheduling, on a small suite of two processes: the Ray chain's tests (by module,
    by a name or parameter that says ray) all in one process, the servers' in one, while tests of
    their own spread. pytest-xdist's loadgroup alone stopped grouping under pytest 9.2 and nothing
    failed (tests/conftest.py)."""
    slow = "import time\ndef sleep():\n    time.sleep(0.4)\n"
    (tmp_path / "test_ray_cluster.py").write_text(slow + "".join(f"def test_node_{k}():\n    sleep()\n" for k in range(4)))
    (tmp_path / "test_tracking_server.py").write_text(slow + "".join(f"def test_outage_{k}():\n    sleep()\n" for k in range(4)))
    (tmp_path / "test_other.py").write_text(
        slow + "import pytest\n"
        + "".join(f"def test_plain_{k}():\n    sleep()\n" for k in range(6))
        + "def test_a_sweep_on_ray_nodes():\n    sleep()\n"
        + "@pytest.mark.parametrize('executor', ['local', 'ray'])\ndef test_progress(executor):\n    sleep()\n")
    (tmp_path / "conftest.py").write_text((ROOT / "tests" / "conftest.py").read_text())
    log = tmp_path / "costs.jsonl"
    env = {"GOPRE_TEST_RESOURCES": str(log), "PATH": "/usr/bin:/bin", "PYTHONPATH": str(ROOT)}
    done = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-n", "2", "--dist",
                           "loadgroup", str(tmp_path)], env=env, cwd=tmp_path, capture_output=True, text=True)
    assert done.returncode == 0, done.stdout + done.stderr
    lines = costs.read_costs(log)
    chains = {c.test.split("::", 1)[1]: c.chain_name for c in lines}
    assert chains["test_a_sweep_on_ray_nodes"] == chains["test_progress[ray]"] == chains["test_node_0"] == "ray"
    assert chains["test_progress[local]"] is None and chains["test_outage_0"] == "servers"
    workers = {}
    for c in lines:
        workers.setdefault(c.chain_name, set()).add(c.worker)
    assert len(workers["ray"]) == 1 and len(workers["servers"]) == 1, workers
    assert len(workers[None]) == 2, workers  # the rest is shared out
