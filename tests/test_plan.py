"""``pipeline-run ... plan=true``: the real command prints the job table, marks finished jobs,
estimates from finished jobs of the same kind, exits 2 on a config error, and starts nothing."""

import subprocess
import sys
from pathlib import Path

import pandas as pd
from hydra import compose, initialize_config_dir

from pipeline.cli.run import CONF_DIR
from pipeline.experiment.build import expand_jobs

BIN = Path(sys.executable).parent
COMMON = ["experiment=debug", "executor=local", "tracking=none", "seeds=[0,1]"]


def run_plan(*overrides):
    return subprocess.run([str(BIN / "pipeline-run"), *COMMON, "plan=true", *overrides],
                          capture_output=True, text=True, timeout=120)


def test_plan_lists_jobs_marks_finished_ones_and_estimates_the_rest(tmp_path):
    out = tmp_path / "sweep"
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        jobs = expand_jobs(compose("config", [*COMMON, f"output_dir={out}"]))
    done = next(j for j in jobs if j.method == "gopre" and j.seed == 0)
    out.mkdir()
    pd.DataFrame([{"config_hash": done.config_hash, "kind": "final", "status": "FINISHED",
                   "dataset": done.dataset, "scene": done.scene, "method": "gopre", "setting": "",
                   "wall_seconds": 150.0, "code_version": None}]).to_parquet(out / "records.parquet")
    proc = run_plan(f"output_dir={out}")
    assert proc.returncode == 0, proc.stderr
    lines = {line.split()[6]: line for line in proc.stdout.splitlines() if line[:1].isdigit()}
    assert set(lines) == {j.config_hash for j in jobs} and len(jobs) == 4
    assert "finished" in lines[done.config_hash]
    other_gopre = next(j for j in jobs if j.method == "gopre" and j.seed == 1)
    assert lines[other_gopre.config_hash].split()[-4:] == ["to", "run", "2", "min"]  # 150 s, as the finished gopre
    random0 = next(j for j in jobs if j.method == "random" and j.seed == 0)
    assert lines[random0.config_hash].endswith("unknown")
    assert "4 jobs, 1 finished, 3 to run; about 8 min on 1 parallel slot(s)" in proc.stdout
    assert not (out / "jobs").exists() and not (out / "jobs.json").exists()


def test_plan_with_a_bad_key_is_a_config_error_with_exit_2(tmp_path):
    proc = run_plan(f"output_dir={tmp_path}", "protocol.kind=local")
    assert proc.returncode == 2
    assert "config error" in proc.stderr and "protocol.kind: 'local' is not one of global, goal, sparse" in proc.stderr


def test_a_first_jobs_one_time_compilation_is_not_in_the_estimate():
    from pipeline.experiment.plan import _durations
    records = pd.DataFrame([{"config_hash": "a", "kind": "final", "status": "FINISHED", "dataset": "d",
                             "scene": "s", "method": "gopre", "setting": "", "wall_seconds": 150.0,
                             "job_compile_seconds": 30.0},
                            {"config_hash": "b", "kind": "final", "status": "FINISHED", "dataset": "d",
                             "scene": "s", "method": "random", "setting": "", "wall_seconds": 40.0}])
    durations = _durations(records).set_index("method")["wall_seconds"]
    assert durations["gopre"] == 120.0  # the fresh machine's compile left out
    assert durations["random"] == 40.0  # a record from before the column: as it was


def test_plan_prints_the_schedule_as_run_and_the_events_densify_settle_holds(tmp_path):
    """tiny at 100 steps a view: rounds of 200 and 300 steps, then 400 (900 in all), so the 240-step
    recipe runs x3.75 and an overridden value with it (densify.stop 100 -> 375); densification
    from 180 every 120 steps: 240 and 360, the latter 140 before the evaluation at 500, which a
    settle of 150 holds (by hand)."""
    proc = run_plan(f"output_dir={tmp_path}", "splat.epochs_per_view=100", "splat.fit.densify.stop=100",
                    "+splat.densify_settle=150")
    assert proc.returncode == 0, proc.stderr
    text = proc.stdout
    assert "the rounds train 200, 300 steps, evaluating at step 200, 500; then 400 after the last pick" in text
    assert "900 steps in all, so the recipe of 240 runs rescaled x3.75" in text
    for line in ("fit.densify.stop = 100 -> 375", "fit.densify.start = 48 -> 180", "fit.densify.interval = 32 -> 120"):
        assert f"    {line}\n" in text
    assert "  density control: 2 densifications (steps 240 to 360), no periodic opacity resets\n" in text
    assert "densify_settle=150 holds these density events: densify at 360 (140 before the evaluation at 500)\n" in text
    plain = run_plan(f"output_dir={tmp_path}").stdout  # the debug preset as written: 240 steps
    assert "240 steps in all: the recipe runs as written" in plain
    assert ("before an evaluation (+splat.densify_settle=N holds those in the last N steps): "
            "densify at 96 (4 before the evaluation at 100)\n") in plain


def test_plan_says_when_an_episode_has_no_density_control(tmp_path):
    """densify.stop=0 (rescaled to 1, below start): no step densifies, prunes or resets."""
    text = run_plan(f"output_dir={tmp_path}", "splat.fit.densify.stop=0").stdout
    assert "  density control: none in the episode (no densification, prune or periodic opacity reset" in text
    assert "densify at" not in text
