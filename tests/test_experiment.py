"""The sweep pipeline with real Hydra, Ray and MLflow (no mocks): presets, executors, tracking,
resume, retries and failures."""

import glob
import json
import os
import re
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from hydra import compose, initialize_config_dir
from hydra.errors import ConfigCompositionException
from omegaconf import OmegaConf

from tests.conftest import free_port
from pipeline.cli.run import CONF_DIR
from pipeline.experiment.episode_settings import ConfigError
from pipeline.experiment.build import expand_jobs
from pipeline.experiment.provenance import code_version
from pipeline.experiment.records import RecordsFile, records_from_mlflow
from pipeline.experiment.sweep import run_sweep
from pipeline.report.paper import load_paper_tables, paper_report
from pipeline.report.report import load_records

PRESETS = sorted(Path(p).stem for p in glob.glob(str(CONF_DIR / "experiment" / "*.yaml")))
TINY = ["splat=tiny", "splat.iterations=100", "dataset=[generated]", "dataset.generated.generate.size=32",
        "dataset.generated.generate.n_train=12", "dataset.generated.generate.n_test=6",
        "protocol.initial_views=2", "protocol.budget=3", "protocol.probes=3", "uncertainty.train_views=3",
        "uncertainty.iterations=60", "uncertainty.map_views=1", "uncertainty.methods=[gopre,fisherrf]"]


def composed(overrides):
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        return compose("config", overrides)


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    return tmp_path_factory.mktemp("sweeps")


@pytest.mark.parametrize("preset", PRESETS)
def test_every_preset_composes_at_paper_scale_and_says_how_to_run_it(preset, tmp_path):
    text = (CONF_DIR / "experiment" / f"{preset}.yaml").read_text()
    assert text.startswith("# @package _global_") and "gopre-run experiment=" + preset in text
    twin = []
    if re.search(r"^twin:", text, re.M):  # a preset off the pool on a real scene names its twin (a file that must exist)
        assert "gopre-data twin" in text  # and says how to make it
        (tmp_path / "twin.ply").write_bytes(b"")
        twin = [f"twin={tmp_path / 'twin.ply'}"]
    jobs = expand_jobs(composed([f"experiment={preset}", "data_root=/datasets", *twin]))
    assert jobs and len({j.config_hash for j in jobs}) == len(jobs)
    if preset not in ("demo", "debug", "science", "science_ablation", "capture_alexander"):  # CPU-scale presets
        assert jobs[0].splat["preset"] == "paper"
        assert all(j.scene_path.startswith("/datasets/") for j in jobs if j.generate is None)  # generated: beside the outputs


def test_method_presets_carry_their_protocol_and_splat_overrides():
    """fisherrf_released reloads the model after each pick as the released code does; the other
    methods keep the sweep's policy; popgs defaults to the POp-GS paper's block variant."""
    jobs = {j.method: j for j in expand_jobs(composed([
        "method=[fisherrf,fisherrf_released,popgs,popgs_diag]", "splat.post_selection=continue"]))}
    assert jobs["fisherrf_released"].splat["post_selection"] == "reload"
    assert jobs["fisherrf_released"].options == {"lam": 1e-6, "hessian": "fisherrf_released"}
    assert jobs["fisherrf"].splat["post_selection"] == "continue"
    assert jobs["popgs"].options["variant"] == "block" and jobs["popgs_diag"].options["variant"] == "diag"
    with pytest.raises(ConfigError, match="method.fisherrf.options.hessian: 'nope' is not one of exact, fisherrf_released"):
        expand_jobs(composed(["method=[fisherrf]", "+method.fisherrf.options.hessian=nope"]))


ABLATIONS = sorted(p.stem for p in (CONF_DIR / "ablation").glob("*.yaml"))


@pytest.mark.parametrize("ablation", ABLATIONS)
def test_every_science_ablation_is_one_axis_on_lego_with_three_seeds(ablation):
    jobs = expand_jobs(composed(["experiment=science_ablation", f"ablation={ablation}", "data_root=/datasets"]))
    assert {j.sweep for j in jobs} == {f"science_ablation_{ablation}"}
    assert {j.scene for j in jobs} == {"lego"} and {j.seed for j in jobs} == {0, 1, 2}
    axes = {tuple(j.axes) for j in jobs}
    assert len(axes) == 1 and len(next(iter(axes))) == 1  # one axis
    values = {tuple(j.axes.values()) for j in jobs}
    assert len(values) >= 2 and len(jobs) == 3 * len(values) * len({j.method for j in jobs})


def test_the_fisherrf_policy_ablation_crosses_both_hessians_with_both_policies():
    """The ablation sets its methods (it comes after the experiment in the defaults), and its axis
    overrides the policy that fisherrf_released's preset carries."""
    jobs = expand_jobs(composed(["experiment=science_ablation", "ablation=fisherrf_policy", "data_root=/d"]))
    cells = {(j.method, j.options.get("hessian", "exact"), j.splat["post_selection"]) for j in jobs}
    assert cells == {(m, h, p) for m, h in (("fisherrf", "exact"), ("fisherrf_released", "fisherrf_released"))
                     for p in ("reset_opacity", "reload")}


@pytest.mark.parametrize("preset", PRESETS)
def test_every_preset_runs_in_its_tiny_form(preset, base):
    cfg = composed([f"experiment={preset}", *TINY, "executor=local", "tracking=none",
                    f"output_dir={base / ('tiny_' + preset)}", "seeds=[0]"])
    OmegaConf.set_struct(cfg, False)
    cfg.method = {k: cfg.method[k] for k in list(cfg.method)[:1]}  # the tiny form: one method
    cfg.sweep = OmegaConf.create({k: {kk: [v[0]] for kk, v in vals.items()} for k, vals in cfg.sweep.items()})
    summary = run_sweep(cfg)
    assert summary.failed == 0 and summary.finished == summary.jobs >= 1
    _, paper_tables = load_paper_tables()
    if preset in paper_tables:  # `pipeline-report --paper` on the preset's own tiny sweep
        text = paper_report(load_records(base / ("tiny_" + preset)))
        assert text.startswith(f"## Beside the paper: {paper_tables[preset].paper}")
        assert "claims about this table" in text or "No finished episode" in text


def test_unknown_keys_and_bad_values_fail_at_start_up_naming_the_key(base):
    with pytest.raises(ConfigCompositionException, match="colour"):
        composed(["splat.colour=1"])
    with pytest.raises(ConfigCompositionException, match="nosuchmethod"):
        composed(["method=[nosuchmethod]"])
    with pytest.raises(ConfigError, match="method.gopre.*tau"):
        expand_jobs(composed(["method.gopre.options.tau=-1"]))
    with pytest.raises(ConfigError, match="data_root is not set.*blender"):
        expand_jobs(composed(["dataset=[blender]", "data_root=null"]))
    with pytest.raises(ConfigError, match="post_selection"):
        expand_jobs(composed(["splat.post_selection=restart"]))


@pytest.mark.parametrize("override,match", [
    ("splat.image_width=0", r"splat.image_width: 0 is not an integer >= 8, or null"),
    ("splat.iterations=-5", r"splat.iterations: -5 is not an integer >= 1"),
    ("splat.max_gaussians=0", r"splat.max_gaussians: 0 is not an integer >= 1"),
    ("job.threads=0", r"job.threads: 0 is not an integer in \[1, 4096\]"),
    ("job.retries=-1", r"job.retries: -1 is not an integer in \[0, 100\]"),
    ("job.renders=-2", r"job.renders: -2 is not an integer in \[0, 10000\]"),
    ("seeds=[-1]", r"seeds: a seed must be >= 0, got \[-1\]"),
])
def test_values_that_used_to_pass_silently_or_fail_late_are_config_errors(override, match):
    with pytest.raises(ConfigError, match=match):
        expand_jobs(composed(["dataset=[generated]", override]))


def metrics_of(frame):
    final = frame[frame["kind"] == "final"].sort_values("method")
    rounds = frame[frame["kind"] == "round"].sort_values(["method", "num_views"])
    return final[["method", "psnr", "ssim", "selected"]].to_dict("records"), rounds["psnr"].tolist()


@pytest.mark.slow
def test_demo_tiny_on_ray_with_mlflow_equals_local_and_yields_a_table(base, ray_session, tmp_path):
    common = ["experiment=demo", *TINY]
    ray_dir, local_dir = base / "demo_ray", base / "demo_local"
    summary = run_sweep(composed([*common, "executor=ray", "tracking=mlflow", f"output_dir={ray_dir}"]))
    assert summary.finished == 4 and summary.failed == 0
    local = run_sweep(composed([*common, "executor=local", "tracking=none", f"output_dir={local_dir}"]))
    assert local.finished == 4
    ray_records, local_records = RecordsFile(ray_dir).frame, RecordsFile(local_dir).frame
    assert metrics_of(ray_records) == metrics_of(local_records)
    # MLflow holds one parent and four children with tags, params, per-round metrics, artifacts
    from mlflow import MlflowClient
    client = MlflowClient(summary.tracking_uri)
    exp = client.get_experiment_by_name("demo")
    runs = client.search_runs([exp.experiment_id], "tags.config_hash != ''")
    assert len(runs) == 4 and all(r.info.status == "FINISHED" for r in runs)
    run = runs[0]
    parent = run.data.tags["mlflow.parentRunId"]
    assert client.get_run(parent).data.tags["kind"] == "sweep"
    assert {"method", "dataset", "scene", "protocol", "seed", "config_hash"} <= set(run.data.tags)
    assert run.data.params["protocol.budget"] == "3"
    history = client.get_metric_history(run.info.run_id, "test_psnr")
    assert sorted(m.step for m in history) == [2, 3]  # step = number of views
    artifacts = {a.path for a in client.list_artifacts(run.info.run_id)}
    assert {"selected_views.json", "renders", "uncertainty", "config.json", "result.json", "model.ply"} <= artifacts
    # the final model's ground truth | render | error | variance per shown view
    from PIL import Image
    row = client.download_artifacts(run.info.run_id, "uncertainty", str(tmp_path / "u"))
    shapes = {Image.open(p).size for p in Path(row).glob("*.png")}
    assert shapes == {(4 * 32, 32)}, shapes
    # the sweep's figures on the parent run (the qualitative grid, the curves)
    figures = {a.path for a in client.list_artifacts(parent, "figures")}
    assert {"figures/qualitative.png", "figures/psnr_vs_views.png"} <= figures, figures
    # pipeline-view finds the job folder of an MLflow run
    from pipeline.view.run import folder_of_mlflow_run
    assert folder_of_mlflow_run(summary.tracking_uri, run.info.run_id).resolve() == \
        (ray_dir / "jobs" / run.data.tags["config_hash"]).resolve()
    # the final model as a standard PLY, in MLflow and in the job folder, exportable from either
    from pipeline.cli.export import main as export_main
    from pipeline.splat import ply
    job_dir = ray_dir / "jobs" / run.data.tags["config_hash"]
    final = ray_records.query("kind == 'final' and config_hash == @run.data.tags['config_hash']")
    assert len(ply.load(job_dir / "artifacts" / "model.ply")) == int(final["num_gaussians"].iloc[0])
    assert export_main([run.info.run_id, "--mlflow-uri", summary.tracking_uri, "--format", "splat",
                        "--out", str(tmp_path / "m.splat")]) == 0
    assert (tmp_path / "m.splat").stat().st_size == 32 * int(final["num_gaussians"].iloc[0])
    # the report reads the records (and MLflow) and makes the table and the figures
    from pipeline.report.report import make_report
    report = make_report(ray_dir, tmp_path / "report")
    for method in ("gopre", "fisherrf", "random", "coverage"):
        assert f"| {method} |" in report["tables"]
    assert {"psnr_vs_views.png", "qualitative.png"} <= set(report["figures"])
    from_mlflow = records_from_mlflow(summary.tracking_uri, "demo")
    assert sorted(from_mlflow[from_mlflow["kind"] == "final"]["psnr"].round(6)) == \
        sorted(ray_records[ray_records["kind"] == "final"]["psnr"].round(6))
    # the report built from MLflow is the report built from the records file (LPIPS note included)
    mlflow_report = make_report(ray_dir, tmp_path / "report_mlflow", frame=from_mlflow)
    assert mlflow_report["tables"] == report["tables"]
    assert "LPIPS disabled in the config" in report["tables"]


def test_an_episode_off_the_pool_round_trips_through_mlflow(base):
    """gopre_search's rounds: which ones took a searched pose, their scores and the captured poses
    come back from MLflow as the records file has them."""
    out = base / "off_pool_mlflow"
    summary = run_sweep(composed(["experiment=debug", *TINY, f"output_dir={out}", "executor=local",
                                  "tracking=mlflow", "method=[gopre_search]", "job.round_images=0",
                                  "protocol.budget=6", "method.gopre_search.world.search.evaluations=8"]))
    assert summary.finished == 1
    columns = ["num_views", "search_taken", "search_score", "search_best_start_score", "search_best_pool_score",
               "poses"]
    stored = RecordsFile(out).frame
    from_mlflow = records_from_mlflow(summary.tracking_uri, "debug")
    for kind in ("round", "final"):
        a = stored[stored["kind"] == kind].sort_values("num_views")
        b = from_mlflow[from_mlflow["kind"] == kind].sort_values("num_views")
        cols = columns if kind == "round" else ["poses"]
        pd.testing.assert_frame_equal(a[cols].reset_index(drop=True), b[cols].reset_index(drop=True),
                                      check_dtype=False)
    assert set(stored["search_taken"].dropna()) == {"search", "pool"}  # both kinds of round made the trip
    assert set(stored["world"]) == set(from_mlflow["world"]) == {"generated"}  # where its views came from


@pytest.mark.slow
def test_relaunch_skips_finished_jobs_and_runs_only_new_ones(base, capsys):
    out = base / "resume"
    common = ["experiment=debug", *TINY, f"output_dir={out}", "executor=local", "tracking=mlflow"]
    first = run_sweep(composed([*common, "method=[random]"]))
    assert (first.finished, first.skipped) == (1, 0)
    again = run_sweep(composed([*common, "method=[random,coverage]"]))
    assert (again.jobs, again.skipped, again.finished) == (2, 1, 1)
    frame = RecordsFile(out).frame  # tidy: one final row per job, round rows per views
    assert set(frame["kind"]) == {"round", "final"}
    assert frame[frame["kind"] == "final"]["config_hash"].is_unique and len(frame[frame["kind"] == "final"]) == 2
    assert set(frame["code_version"]) == {code_version()}
    # jobs computed by other code are kept on relaunch, and the sweep says so
    records = RecordsFile(out)
    records.frame.loc[records.frame["method"] == "random", "code_version"] = "0123456789ab"
    records.add([])
    capsys.readouterr()
    run_sweep(composed([*common, "method=[random,coverage]"]))
    assert "1 skipped job(s) were computed by code 0123456789ab" in capsys.readouterr().out
    # MLflow alone is enough to skip: drop the records file
    (out / "records.parquet").unlink()
    third = run_sweep(composed([*common, "method=[random,coverage]"]))
    assert (third.skipped, third.finished) == (2, 0)


def broken_scene(good: Path, folder: Path) -> Path:
    """A copy of a generated scene whose training images (but the first) are not PNGs."""
    import shutil
    shutil.copytree(good, folder)
    for png in sorted((folder / "train").glob("r_*.png"))[1:]:
        png.write_bytes(b"not a png")
    return folder


def test_a_corrupt_scene_is_refused_before_anything_starts(base):
    """Every scene is read and every protocol built before Ray or MLflow start; all problems are
    listed at once, each naming its dataset key."""
    out = base / "refused"
    cfg = composed(["experiment=debug", *TINY, f"output_dir={out}", "method=[random]", "tracking=mlflow"])
    good = Path(expand_jobs(cfg)[0].scene_path).resolve()  # <out>/../scenes/...: out is not made yet
    if not (good / "transforms_test.json").exists():
        run_sweep(composed(["experiment=debug", *TINY, f"output_dir={base / 'gen'}", "method=[random]"]))
    broken_scene(good, out / "data" / "broken")
    OmegaConf.set_struct(cfg, False)
    cfg.dataset.broken = {"format": "blender", "root": str(out / "data"), "scenes": ["broken", "nosuch"],
                          "generate": None}
    with pytest.raises(ConfigError) as err:
        run_sweep(cfg)
    text = str(err.value)
    assert text.startswith("2 problem(s), nothing was started")
    assert "dataset.broken scene 'broken'" in text and "r_" in text and ".png" in text
    assert "dataset.broken scene 'nosuch'" in text and "no such folder" in text
    assert not (out / "mlruns").exists() and not (out / "jobs").exists() and not (out / "mlflow.db").exists()


@pytest.mark.slow
def test_a_raising_job_is_retried_then_failed_while_the_others_finish(base, monkeypatch):
    """A job that raises is retried, then recorded FAILED while the others finish; a relaunch
    reruns exactly the FAILED jobs (records and MLflow)."""
    import shutil

    import pipeline.experiment.job as job_module
    out = base / "failing"
    cfg = composed(["experiment=debug", *TINY, f"output_dir={out}", "method=[random]", "job.retries=1",
                    "tracking=mlflow"])
    run_sweep(cfg)  # generates the good scene and runs it
    good = Path(expand_jobs(cfg)[0].scene_path)
    shutil.copytree(good, out / "data" / "flaky")
    real = job_module.run_episode

    def failing_on_flaky(scene, *args, **kwargs):
        if Path(scene.root).name == "flaky":
            raise OSError("injected I/O failure on r_flaky")  # transient: retried
        return real(scene, *args, **kwargs)
    monkeypatch.setattr(job_module, "run_episode", failing_on_flaky)
    OmegaConf.set_struct(cfg, False)
    cfg.dataset.flaky = {"format": "blender", "root": str(out / "data"), "scenes": ["flaky"], "generate": None}
    cfg.method = {"random": cfg.method.random, "coverage": {"strategy": "coverage", "options": {}}}
    summary = run_sweep(cfg)
    assert summary.failed == 2 and summary.finished == 1 and summary.skipped == 1
    frame = RecordsFile(out).frame
    failed = frame[frame["status"] == "FAILED"]
    assert len(failed) == 2 and (failed["attempts"] == 2).all()
    assert failed["error"].str.contains("injected I/O failure on r_flaky").all()
    hash_ = failed["config_hash"].iloc[0]
    assert "traceback" in (out / "jobs" / hash_ / "artifacts" / "traceback.txt").read_text().lower()
    log = (out / "jobs" / hash_ / "log.txt").read_text()
    assert "attempt 1/2 failed" in log and "attempt 2/2 failed" in log
    # repaired and relaunched: exactly the two FAILED jobs run again, and now finish
    monkeypatch.setattr(job_module, "run_episode", real)
    again = run_sweep(cfg)
    assert (again.skipped, again.finished, again.failed) == (2, 2, 0)
    frame = RecordsFile(out).frame.query("kind == 'final'")
    assert len(frame) == 4 and set(frame["status"]) == {"FINISHED"}
    assert set(failed["config_hash"]) <= set(frame["config_hash"])
    (out / "records.parquet").unlink()  # MLflow alone now knows all four as FINISHED
    assert run_sweep(cfg).skipped == 4


def start_mlflow_server(folder: Path, port: int) -> subprocess.Popen:
    """A real ``mlflow server`` on a SQLite store in ``folder``, up and answering /health."""
    server = subprocess.Popen(
        [sys.executable, "-m", "mlflow", "server", "--host", "127.0.0.1", "--port", str(port),
         "--backend-store-uri", f"sqlite:///{folder / 'server.db'}",
         "--default-artifact-root", str(folder / "server-artifacts"), "--workers", "1"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env={**os.environ, "MLFLOW_ENABLE_ARTIFACTS_PROXY": "false"})
    deadline = time.time() + 120
    while True:
        try:
            if urllib.request.urlopen(f"http://127.0.0.1:{port}/health", timeout=2).status == 200:
                return server
        except OSError:
            if time.time() > deadline or server.poll() is not None:
                server.kill()
                raise RuntimeError("mlflow server did not come up") from None
            time.sleep(0.5)


def stop(server: subprocess.Popen) -> None:
    server.terminate()
    server.wait(timeout=30)


@pytest.mark.slow
def test_a_tracking_server_that_goes_away_loses_nothing_and_a_sync_replays_it(base, tmp_path, capsys):
    """The server stops after the first job is tracked: the sweep goes on, records keep every
    result, the launch names the untracked runs; with the server back, tracking_sync=true replays
    them and MLflow then has every job FINISHED."""
    import pipeline.experiment.tracking as tracking_module
    port = free_port()
    uri = f"http://127.0.0.1:{port}"
    out = base / "server_down"
    overrides = ["experiment=debug", *TINY, "method=[random,coverage]", "executor=local",
                 "tracking=mlflow", f"tracking.uri={uri}", "tracking.replay_wait_s=0", f"output_dir={out}"]
    server = start_mlflow_server(tmp_path, port)  # (replay_wait_s=0: the sweep does not wait for it to return)
    real_log_job = tracking_module.MlflowTracker.log_job
    calls = []

    def log_then_stop_the_server(self, job, outcome):
        calls.append(job.config_hash)
        run_id = real_log_job(self, job, outcome)
        if len(calls) == 1:
            stop(server)  # the server goes away after the first tracked job
        return run_id
    try:
        tracking_module.MlflowTracker.log_job = log_then_stop_the_server
        summary = run_sweep(composed(overrides))
    finally:
        tracking_module.MlflowTracker.log_job = real_log_job
        stop(server)
    assert summary.finished == 2 and summary.failed == 0 and len(summary.untracked) == 1
    assert "1 finished job(s) could not be tracked" in capsys.readouterr().out
    frame = RecordsFile(out).frame.query("kind == 'final'")
    assert len(frame) == 2 and set(frame["status"]) == {"FINISHED"}
    server = start_mlflow_server(tmp_path, port)  # back, on the same store
    try:
        from pipeline.experiment.sweep import sync_tracking
        result = sync_tracking(composed([*overrides, "tracking_sync=true"]))
        assert sorted(result["synced"]) == sorted(summary.untracked) and result["unknown"] == []
        runs = records_from_mlflow(uri, "debug").query("kind == 'final'")
        assert sorted(runs["config_hash"]) == sorted(frame["config_hash"])
        assert set(runs["status"]) == {"FINISHED"}
        mine = RecordsFile(out).frame.query("kind == 'final'").set_index("config_hash")["psnr"].sort_index()
        theirs = runs.set_index("config_hash")["psnr"].sort_index()
        assert np.allclose(mine.to_numpy(dtype=float), theirs.to_numpy(dtype=float))
        assert RecordsFile(out).frame["run_id"].notna().all()  # the records now name the runs
        assert sync_tracking(composed([*overrides, "tracking_sync=true"]))["synced"] == []  # idempotent
    finally:
        stop(server)


@pytest.mark.slow
def test_a_real_mlflow_server_receives_a_run_over_http(base, tmp_path):
    port = free_port()
    server = start_mlflow_server(tmp_path, port)
    uri = f"http://127.0.0.1:{port}"
    try:
        summary = run_sweep(composed(["experiment=debug", *TINY, "method=[random]", "executor=local",
                                      "tracking=mlflow", f"tracking.uri={uri}", f"output_dir={base / 'server'}"]))
        assert summary.finished == 1 and summary.tracking_uri == uri
        frame = records_from_mlflow(uri, "debug")
        final = frame[frame["kind"] == "final"]
        assert len(final) == 1 and final["method"].iloc[0] == "random" and final["psnr"].iloc[0] > 5
    finally:
        stop(server)


def test_code_version_names_the_commit_and_uncommitted_changes(tmp_path):
    import subprocess
    from pipeline.experiment.provenance import stale_versions
    repo = tmp_path / "repo"
    repo.mkdir()
    git = ["git", "-C", str(repo), "-c", "user.email=t@t", "-c", "user.name=t"]
    subprocess.run([*git, "init", "-q"], check=True)
    (repo / "a.txt").write_text("1")
    subprocess.run([*git, "add", "a.txt"], check=True)
    subprocess.run([*git, "commit", "-qm", "one"], check=True)
    head = subprocess.run([*git, "rev-parse", "--short=12", "HEAD"], capture_output=True, text=True).stdout.strip()
    assert code_version(repo) == head
    (repo / "a.txt").write_text("2")
    code_version.cache_clear()
    assert code_version(repo) == head + "-dirty"
    assert code_version(tmp_path / "plain").startswith("gopre ")  # not a checkout: the package version
    assert stale_versions({"h1": "a", "h2": "b", "h3": "b", "h4": None}, "a") == {"b": 2, "unrecorded": 1}


@pytest.mark.slow
@pytest.mark.parametrize("executor", ["local", "ray"])
def test_round_progress_reaches_the_driver_and_mlflow_while_jobs_run(executor, base, ray_session,
                                                                    capsys):
    out = base / f"progress_{executor}"
    summary = run_sweep(composed(["experiment=debug", *TINY, "method=[random,coverage]",
                                  f"executor={executor}", "tracking=mlflow", f"output_dir={out}"]))
    assert summary.finished == 2
    lines = capsys.readouterr().out.splitlines()
    for method in ("random", "coverage"):
        mine = [ln for ln in lines if f"] {method} on " in ln and " views, curve PSNR " in ln]
        # budget 3 from 2 views: one selection round, then the final evaluation; one line each
        assert [ln.split(": ", 1)[1].split(",")[0] for ln in mine] == ["round 1/2", "final"], lines
        assert ", 2 views, " in mine[0] and ", 3 views, " in mine[1]
        done = next(i for i, ln in enumerate(lines) if f"| {method} on " in ln)
        assert lines.index(mine[-1]) < done  # heard before the job's end line
        assert "curve PSNR" in mine[0] and "(on 6 test views)" in mine[0]  # which PSNR each line is
        assert "FINISHED test PSNR " in lines[done] and "(all 6 test views)" in lines[done]
    logged = (out / "sweep.log").read_text().splitlines()  # the same lines, timestamped
    assert [ln.split(" INFO ", 1)[1] for ln in logged if " INFO [debug]" in ln] == \
        [ln for ln in lines if ln.startswith("[debug]")]
    from mlflow import MlflowClient
    client = MlflowClient(summary.tracking_uri)
    exp = client.get_experiment_by_name("debug")
    for run in client.search_runs([exp.experiment_id], "tags.config_hash != ''"):
        steps = sorted(m.step for m in client.get_metric_history(run.info.run_id, "test_psnr"))
        assert steps == [2, 3] and run.info.status == "FINISHED"  # logged live once, not twice
        wall = RecordsFile(out).frame.query("kind == 'final' and run_id == @run.info.run_id")["wall_seconds"].iloc[0]
        assert (run.info.end_time - run.info.start_time) / 1000 >= wall  # the run spans the job, not its rounds


def test_a_degraded_final_model_is_flagged_in_records_mlflow_and_output(base, capsys, monkeypatch):
    """A schedule that evaluates right after the last opacity reset (as the old CPU preset did on
    real scenes) must not pass silently into a table."""
    from pipeline.active import plan as plan_module
    from pipeline.active.schedule import Schedule
    real = plan_module.views_schedule
    monkeypatch.setattr(plan_module, "views_schedule", lambda initial, budget, cfg: Schedule(
        real(initial, budget, cfg).round_views, real(initial, budget, cfg).round_iterations, 0,
        sum(real(initial, budget, cfg).round_iterations)))
    out = base / "degraded"
    summary = run_sweep(composed(["experiment=debug", *TINY, "splat.iterations=null", "method=[coverage]",
                                  "executor=local", "tracking=mlflow", f"output_dir={out}"]))
    assert summary.finished == 1
    warning = [ln for ln in capsys.readouterr().out.splitlines() if "degraded model" in ln]
    assert len(warning) == 1 and "coverage on " in warning[0]
    final = RecordsFile(out).frame.query("kind == 'final'").iloc[0]
    assert bool(final["degraded"]) and final["curve_psnr_drop"] > 3
    from mlflow import MlflowClient
    client = MlflowClient(summary.tracking_uri)
    run = client.get_run(final["run_id"])
    assert run.data.tags["degraded"] == "true"
    from_mlflow = records_from_mlflow(summary.tracking_uri, "debug").query("kind == 'final'")
    assert bool(from_mlflow["degraded"].iloc[0])


def test_a_second_launch_on_a_held_output_dir_is_refused(base):
    from pipeline.experiment.lock import SweepLock
    out = base / "held"
    with SweepLock(out):  # as a running sweep would hold it
        with pytest.raises(ConfigError, match=f"output_dir {out} is held by a running sweep"):
            run_sweep(composed(["experiment=debug", *TINY, f"output_dir={out}", "method=[random]"]))
        assert not (out / "jobs.json").exists()


def test_a_relaunch_after_a_killed_driver_closes_its_runs_left_running(base):
    """A SIGKILLed driver leaves its lock and its MLflow runs RUNNING: the relaunch takes the stale
    lock over, marks those runs (of this output folder only) KILLED, and finishes the sweep."""
    import json as json_module

    from mlflow import MlflowClient

    from pipeline.experiment.lock import HOLDER_NAME
    from pipeline.experiment.tracking import MlflowTracker
    out = base / "killed_driver"
    cfg = composed(["experiment=debug", *TINY, "method=[random]", "tracking=mlflow", f"output_dir={out}"])
    tracker = MlflowTracker(None, out, "debug")  # what the killed driver had opened
    tracker.start({}, 1)
    child = tracker._child_run(expand_jobs(cfg)[0])
    other = MlflowClient(tracker.uri).create_run(tracker.experiment_id, tags={"output_dir": "/elsewhere"})
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()  # a pid that no longer runs
    (out / HOLDER_NAME).write_text(json_module.dumps({"host": os.uname().nodename, "pid": proc.pid, "since": "x"}))
    summary = run_sweep(cfg)
    assert summary.finished == 1
    client = MlflowClient(tracker.uri)
    assert client.get_run(tracker.parent).info.status == "KILLED" and client.get_run(child).info.status == "KILLED"
    assert client.get_run(other.info.run_id).info.status == "RUNNING"  # another folder's run


@pytest.mark.slow
def test_two_sweeps_at_once_on_one_tracking_server_land_all_their_runs(tmp_path):
    """Two launches of the same preset with different output_dirs, started together against one
    real server (the experiment is created by whichever comes first): every job of both lands."""
    port = free_port()
    server = start_mlflow_server(tmp_path, port)
    uri = f"http://127.0.0.1:{port}"
    try:
        procs = [subprocess.Popen([str(Path(sys.executable).parent / "pipeline-run"), "experiment=debug", *TINY,
                                   "method=[random,coverage]", "executor=local", "tracking=mlflow",
                                   f"tracking.uri={uri}", f"output_dir={tmp_path / name}"],
                                  stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
                 for name in ("a", "b")]
        outs = [p.communicate(timeout=600)[0] for p in procs]
        assert [p.returncode for p in procs] == [0, 0], outs
        runs = records_from_mlflow(uri, "debug").query("kind == 'final'")
        assert len(runs) == 4 and set(runs["status"]) == {"FINISHED"}  # 2 jobs x 2 sweeps
        from mlflow import MlflowClient
        client = MlflowClient(uri)
        exp = client.get_experiment_by_name("debug")
        children = client.search_runs([exp.experiment_id], "tags.config_hash != ''")
        assert len(children) == 4 and {r.info.status for r in children} == {"FINISHED"}
        assert {r.data.tags["output_dir"] for r in children} == {str((tmp_path / n).resolve()) for n in "ab"}
    finally:
        stop(server)


def test_each_round_logs_renders_variance_maps_and_the_pick_as_mlflow_images(base):
    from mlflow import MlflowClient
    out = base / "round_images"
    summary = run_sweep(composed(["experiment=debug", *TINY, "method=[random]", "tracking=mlflow",
                                  "job.round_images=1", f"output_dir={out}"]))
    assert summary.finished == 1
    client = MlflowClient(summary.tracking_uri)
    exp = client.get_experiment_by_name("debug")
    (run,) = client.search_runs([exp.experiment_id], "tags.config_hash != ''")
    names = [a.path for a in client.list_artifacts(run.info.run_id, "images")]
    rounds = RecordsFile(out).frame.query("kind == 'round'").sort_values("num_views")
    assert len(json.loads(rounds["selected"].iloc[0])) == 1  # one pick with 2 views taken
    for key in ("render_test_", "variance_test_", "picked+"):
        assert any(n.startswith(f"images/{key}") and "+step+2+" in n for n in names), (key, names)
    assert not any(n.startswith("images/picked_") for n in names)  # one series, not a key per view id


def test_a_truncated_image_the_protocol_uses_is_refused_before_any_job(base, tmp_path):
    import shutil
    from pipeline.experiment.sweep import validate_sweep
    jobs = expand_jobs(composed(["experiment=debug", *TINY, "method=[random]", f"output_dir={tmp_path / 'o'}"]))
    validate_sweep(jobs)  # generates the tiny scene when it is not there yet
    scene = tmp_path / "copy"
    shutil.copytree(Path(jobs[0].scene_path).resolve(), scene)
    victim = sorted((scene / "train").glob("*.png"))[3]
    victim.write_bytes(victim.read_bytes()[:120])  # a truncated file: its header (and size) still read
    for job in jobs:
        job.scene_path = str(scene)
    with pytest.raises(ConfigError, match=rf"{victim.name}: cannot read image"):  # named, at launch
        validate_sweep(jobs)
    validate_sweep(jobs, decode_images=False)  # the flag for datasets too large to read twice


def test_the_end_of_a_sweep_says_how_to_open_its_runs_page():
    from pipeline.experiment.tracking import mlflow_runs_hint
    assert mlflow_runs_hint("http://host:5000/", "7") == "MLflow runs: http://host:5000/#/experiments/7/runs"
    local = mlflow_runs_hint("sqlite:///o/mlflow.db", "3")
    assert "mlflow ui --backend-store-uri sqlite:///o/mlflow.db" in local
    assert local.endswith("http://127.0.0.1:5000/#/experiments/3/runs")
    assert mlflow_runs_hint(None, None) is None

