"""Bad sweeps are refused by the real ``pipeline-run`` before any job starts: exit status 2 and a
message naming the key or the folder, no traceback, no job folder."""

import subprocess
import sys
import time
from pathlib import Path

import pytest

BIN = Path(sys.executable).parent
pytestmark = pytest.mark.slow  # one real command per case (~10 s each idle)


@pytest.mark.parametrize("overrides,expected", [
    (["dataset.generated.root=/nonexistent", "dataset.generated.generate=null"],
     "dataset.generated scene 'generated': /nonexistent/generated: no such folder"),
    # debug sizes the generated scene, which this list does not select: the shared data is what is missing
    (["dataset=[shared]", "data_root=/data"], "dataset.shared_blender scene 'lego': /data/blender/lego: no such folder"),
    (["protocol.budget=0"], "protocol.budget: 0 is not an integer >= 2, or null"),
    (["seeds=zero"], "seeds: expected a non-empty list of integers, e.g. seeds=[0,1,2], got 'zero'"),
    (["job.threads=0"], "job.threads: 0 is not an integer in [1, 4096]"),
    (["plan=true", "dataset.generated.root=/nonexistent", "dataset.generated.generate=null"],
     "dataset.generated scene 'generated': /nonexistent/generated: no such folder"),
    (["tracking=mlflow", "tracking.uri=http://127.0.0.1:9"],
     "tracking.uri http://127.0.0.1:9 cannot be reached"),
    (["protocol.initial_views=20", "protocol.budget=30"],
     "protocol on dataset.generated scene 'generated': initial_views=20 exceeds the pool of 14 views"),
])
def test_bad_sweeps_exit_2_naming_the_problem_before_any_job(tmp_path, overrides, expected):
    start = time.monotonic()
    proc = subprocess.run([str(BIN / "pipeline-run"), "experiment=debug", f"output_dir={tmp_path / 'o'}",
                           *overrides], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert "config error" in proc.stderr and expected in proc.stderr
    assert "Traceback" not in proc.stderr
    assert not (tmp_path / "o" / "jobs").exists()
    assert time.monotonic() - start < 90  # no minutes of client retries (an unreachable server)


def test_an_unreadable_init_ply_is_refused_before_any_job(tmp_path):
    (tmp_path / "bad.ply").write_bytes(b"ply\nformat ascii 1.0\nend_header\n")
    proc = subprocess.run([str(BIN / "pipeline-run"), "experiment=debug", f"output_dir={tmp_path / 'o'}",
                           f"+splat.init=ply:{tmp_path / 'bad.ply'}"], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2 and f"splat.init: {tmp_path / 'bad.ply'}: no vertex element" in proc.stderr


def test_multirun_is_refused_with_the_one_sweep_syntax_and_help_is_ours(tmp_path):
    proc = subprocess.run([str(BIN / "pipeline-run"), "-m", "method=gopre,random",
                           f"output_dir={tmp_path / 'o'}"], capture_output=True, text=True, timeout=300,
                          cwd=tmp_path)
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert "'method=[gopre,random]'" in proc.stderr and "Traceback" not in proc.stderr
    assert not (tmp_path / "multirun").exists() and not (tmp_path / "o" / "jobs").exists()
    helped = subprocess.run([str(BIN / "pipeline-run"), "--help"], capture_output=True, text=True, timeout=300)
    assert helped.returncode == 0 and helped.stdout.startswith("gopre-run: launch one sweep")
    for needle in ("plan=true", "tracking_sync=true", "+sweep.protocol.probes", "Presets (experiment=...)",
                   "method: activenerf, cover, coverage"):
        assert needle in helped.stdout, needle



def test_an_impossible_output_dir_is_one_config_error_and_a_bad_port_one_line(tmp_path):
    """Both were tracebacks (issue 47); a bad --port also left a process that never exited."""
    from hydra import compose, initialize_config_dir

    from pipeline.cli.run import CONF_DIR
    from pipeline.experiment.episode_settings import ConfigError
    from pipeline.experiment.sweep import run_sweep
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        cfg = compose("config", ["experiment=debug", f"output_dir={blocker / 'out'}"])
    with pytest.raises(ConfigError, match=r"output_dir=.*a_file/out: cannot write there \(Not a directory\)"):
        run_sweep(cfg)
    proc = subprocess.run([str(BIN / "gopre-run"), "experiment=debug", f"output_dir={blocker / 'out'}"],
                          capture_output=True, text=True, timeout=300)  # the command: before Hydra's own folder
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr[-2000:]
    assert f"config error: output_dir={blocker / 'out'}: cannot write there (Not a directory)" in proc.stderr
    for port in ("-1", "99999", "http"):
        view = subprocess.run([str(BIN / "gopre-view"), str(tmp_path), "--port", port], capture_output=True,
                              text=True, timeout=60)
        assert view.returncode == 2 and "Traceback" not in view.stderr
        assert "argument --port: expected a TCP port 1-65535" in view.stderr, view.stderr


@pytest.mark.parametrize("command", [
    ["gopre-eval", "MODEL", "SCENE", "--out", "{bad}/m.json"],
    ["gopre-export", "MODEL", "--out", "{bad}/m.ply"],
    ["gopre-report", "RECORDS", "--out", "{bad}/report"],
    ["gopre-data", "generate", "{bad}/scene"],
])
def test_an_output_path_that_cannot_be_written_is_one_line_before_any_work(command, tmp_path):
    """Each of these wrote a traceback after its work (issue 47)."""
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    bad = blocker / "under"
    model = tmp_path / "m.ply"
    from pipeline.splat import ply
    from pipeline.splat.scenes import random_scene
    ply.save(random_scene(20, seed=0, sh_degree=0), model)
    records = tmp_path / "sweep"
    records.mkdir()
    import pandas as pd
    pd.DataFrame([{"sweep": "s", "kind": "final", "status": "FINISHED", "method": "a", "dataset": "d",
                   "scene": "x", "seed": 0, "psnr": 20.0, "config_hash": "h"}]).to_parquet(records / "records.parquet")
    args = [a.format(bad=bad).replace("MODEL", str(model)).replace("SCENE", str(tmp_path))
            .replace("RECORDS", str(records)) for a in command]
    proc = subprocess.run([str(BIN / args[0]), *args[1:]], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1 and "Traceback" not in proc.stderr, proc.stderr[-2000:]
    assert f"{bad}" in proc.stderr and "cannot write there (Not a directory)" in proc.stderr, proc.stderr


def test_more_threads_than_this_machines_cores_is_said_before_the_jobs_run():
    from types import SimpleNamespace

    from pipeline.experiment.sweep import more_threads_than_cores
    jobs = [SimpleNamespace(execution=SimpleNamespace(threads=t)) for t in (1, 1000)]
    here, there = SimpleNamespace(runs_here=True), SimpleNamespace(runs_here=False)
    line = more_threads_than_cores(here, jobs, cores=2)
    assert line.startswith("warning: job.threads=1000") and "has 2 cores" in line and "job.threads=2" in line
    assert more_threads_than_cores(there, jobs, cores=2) is None  # a cluster's nodes have their own cores
    assert more_threads_than_cores(here, jobs[:1], cores=2) is None and more_threads_than_cores(here, [], 2) is None
