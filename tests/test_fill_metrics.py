"""Records made before metrics version 2 (``ssim`` was scikit-image's): the report never shows
that value as SSIM, and ``gopre-eval --sweep`` fills in 3DGS's SSIM from each job's final model,
equal to what the episode itself computes today, refusing a model that is not the scored one."""

import json
import shutil

import pandas as pd
import pytest

from pipeline.cli.eval import main as eval_main
from pipeline.experiment.fill_metrics import fill_ssim
from pipeline.experiment.layout import SweepFolder
from pipeline.experiment.records import RecordsFile
from pipeline.experiment.sweep import run_sweep
from pipeline.report.report import load_records, make_report
from tests.test_experiment import TINY, composed


@pytest.fixture(scope="module")
def current_sweep(tmp_path_factory):
    out = tmp_path_factory.mktemp("fill") / "current"
    summary = run_sweep(composed(["experiment=debug", *TINY, "method=[random,coverage]", f"output_dir={out}",
                                  "executor=local", "tracking=none"]))
    assert summary.finished == 2
    return out


def as_version_1(src, dst):
    """A copy of the sweep as the code before metrics version 2 wrote it."""
    shutil.copytree(src, dst)
    sweep = SweepFolder(dst)
    for job in json.loads(sweep.jobs_file.read_text()):
        path = sweep.job(job["config_hash"]).result_file
        result = json.loads(path.read_text())
        final = result["final"]
        final["ssim"], final["per_view_ssim"] = final.pop("ssim_skimage"), final.pop("per_view_ssim_skimage")
        del final["metrics_version"], final["ssim_source"]
        for r in result["rounds"]:
            r["test_ssim"] = r.pop("test_ssim_skimage")
        path.write_text(json.dumps(result))
    records = RecordsFile(dst)
    frame = records.frame.assign(ssim=records.frame["ssim_skimage"])
    frame.drop(columns=["ssim_skimage", "metrics_version", "ssim_source"]).to_parquet(records.path, index=False)
    return dst


def finals(folder):
    frame = load_records(folder)
    return frame[frame["kind"] == "final"].set_index("config_hash").sort_index()


def test_a_version_1_sweep_is_reported_without_an_ssim_it_does_not_have(current_sweep, tmp_path):
    old = as_version_1(current_sweep, tmp_path / "old")
    now, before = finals(current_sweep), finals(old)
    assert before["ssim"].isna().all() and before["metrics_version"].eq(1).all()
    assert (before["ssim_skimage"] == now["ssim_skimage"]).all()
    rounds = load_records(old).query("kind == 'round'")
    assert rounds["ssim"].isna().all() and rounds["ssim_skimage"].notna().all()
    report = make_report(old, tmp_path / "report")
    assert "recorded before it (metrics version 1)" in report["tables"]
    for value in before["ssim_skimage"]:  # scikit-image's value is never printed as SSIM
        assert f"{value:.3f}" not in report["tables"]


def test_filling_a_version_1_sweep_gives_back_what_the_episode_computes(current_sweep, tmp_path, capsys):
    old = as_version_1(current_sweep, tmp_path / "old")
    assert eval_main(["--sweep", str(old)]) == 0
    assert "2 filled, 0 already current, 0 refused" in capsys.readouterr().out
    now, filled = finals(current_sweep), finals(old)
    assert filled["ssim"].tolist() == pytest.approx(now["ssim"].tolist(), abs=1e-12)
    assert (filled["ssim"] != filled["ssim_skimage"]).all()
    assert filled["metrics_version"].eq(2).all() and filled["ssim_source"].eq("model.ply").all()
    sweep = SweepFolder(old)
    for config_hash in now.index:
        result = json.loads(sweep.job(config_hash).result_file.read_text())
        truth = json.loads(SweepFolder(current_sweep).job(config_hash).result_file.read_text())
        assert result["final"]["per_view_ssim"] == pytest.approx(truth["final"]["per_view_ssim"], abs=1e-12)
        assert [r["test_ssim"] for r in result["rounds"]] == [None] * len(result["rounds"])  # not kept
        assert [r["test_ssim_skimage"] for r in result["rounds"]] == [r["test_ssim_skimage"] for r in truth["rounds"]]
    rounds = load_records(old).query("kind == 'round'")
    assert rounds["ssim"].isna().all() and rounds["ssim_skimage"].notna().all()
    # nothing left to do
    again = fill_ssim(old)
    assert (again.filled, sorted(again.current)) == ([], sorted(now.index))


def swapped_models_fill(old, capsys) -> tuple[str, str, bytes, str]:
    """Job a's model replaced by job b's, then `gopre-eval --sweep`: (a, b, a's result.json before,
    the output); the fill must refuse a and exit 1."""
    sweep = SweepFolder(old)
    a, b = sorted(finals(old).index)
    shutil.copy(sweep.job(b).model_file, sweep.job(a).model_file)
    untouched = sweep.job(a).result_file.read_bytes()
    assert eval_main(["--sweep", str(old)]) == 1
    return a, b, untouched, capsys.readouterr().out


def test_a_model_that_is_not_the_scored_one_is_refused_and_left_alone(current_sweep, tmp_path, capsys):
    old = as_version_1(current_sweep, tmp_path / "old")
    a, b, untouched, out = swapped_models_fill(old, capsys)
    sweep = SweepFolder(old)
    assert "1 filled, 0 already current, 1 refused" in out and f"refused {a}" in out
    assert "does not reproduce the recorded PSNR" in out
    assert sweep.job(a).result_file.read_bytes() == untouched
    frame = finals(old)
    assert pd.isna(frame.loc[a, "ssim"]) and frame.loc[b, "metrics_version"] == 2


def test_sweep_and_model_arguments_are_exclusive(tmp_path):
    with pytest.raises(SystemExit):
        eval_main(["--sweep", str(tmp_path), "model.ply"])
    with pytest.raises(SystemExit):
        eval_main([])


MEASURED = ("path_length", "unc_", "depth_")  # what fill_uncertainty measures (records columns)


def as_before_uncertainty(src, dst):
    """A copy of the sweep as the code before the final model's uncertainty, camera path and depth
    were measured wrote it."""
    shutil.copytree(src, dst)
    sweep = SweepFolder(dst)
    for job in json.loads(sweep.jobs_file.read_text()):
        path = sweep.job(job["config_hash"]).result_file
        result = json.loads(path.read_text())
        for key in ("uncertainty", "path_length", "depth", "uncertainty_curves"):
            result["final"].pop(key)
        path.write_text(json.dumps(result))
    records = RecordsFile(dst)
    frame = records.frame
    frame.drop(columns=[c for c in frame if c.startswith(MEASURED)]).to_parquet(records.path, index=False)
    return dst


def test_filling_a_sweep_recorded_without_uncertainty_gives_back_what_the_episode_measures(current_sweep, tmp_path,
                                                                                            capsys):
    old = as_before_uncertainty(current_sweep, tmp_path / "old")
    before = finals(old)
    assert not [c for c in before if c.startswith(MEASURED)]
    assert eval_main(["--sweep", str(old)]) == 0
    out = capsys.readouterr().out
    assert "uncertainty, camera path, depth: 2 filled, 0 already current, 0 refused" in out
    now, filled = finals(current_sweep), finals(old)
    columns = [c for c in now if c.startswith(MEASURED)]
    assert {"path_length", "unc_ause_mae_max", "unc_nll", "depth_abs_rel"} <= set(columns)
    for column in columns:
        assert filled[column].tolist() == pytest.approx(now[column].tolist(), rel=1e-6), column
    sweep = SweepFolder(old)
    for config_hash in now.index:
        result = json.loads(sweep.job(config_hash).result_file.read_text())["final"]
        truth = json.loads(SweepFolder(current_sweep).job(config_hash).result_file.read_text())["final"]
        assert result["uncertainty"] == pytest.approx(truth["uncertainty"], rel=1e-6)
        assert result["depth"] == pytest.approx(truth["depth"], rel=1e-6)
        assert result["uncertainty_curves"]["fractions"] == truth["uncertainty_curves"]["fractions"]
        for error in ("mae", "rmse", "dssim"):
            for curve in ("by_uncertainty", "oracle", "random"):
                assert result["uncertainty_curves"][error][curve] == pytest.approx(
                    truth["uncertainty_curves"][error][curve], rel=1e-6, abs=1e-12), (error, curve)
    assert load_records(old).query("kind == 'round'").shape == load_records(current_sweep).query("kind == 'round'").shape
    # the report's uncertainty table now has them
    assert "| random |" in make_report(old, tmp_path / "report")["tables"]
    from pipeline.experiment.fill_metrics import fill_uncertainty
    again = fill_uncertainty(old)
    assert (again.filled, sorted(again.current)) == ([], sorted(now.index))


def test_an_uncertainty_fill_refuses_a_model_that_is_not_the_scored_one(current_sweep, tmp_path, capsys):
    old = as_before_uncertainty(current_sweep, tmp_path / "old")
    a, b, untouched, out = swapped_models_fill(old, capsys)
    sweep = SweepFolder(old)
    assert "uncertainty, camera path, depth: 1 filled, 0 already current, 1 refused" in out
    assert sweep.job(a).result_file.read_bytes() == untouched
    frame = finals(old)
    assert pd.isna(frame.loc[a, "unc_nll"]) and not pd.isna(frame.loc[b, "unc_nll"])


def test_a_sweep_measured_without_the_curves_gets_them_and_keeps_its_values_or_is_refused(current_sweep, tmp_path,
                                                                                       capsys):
    """The state of a sweep filled before the curves were kept: uncertainty measured, no curves. The
    fill adds the curves; a recorded value the code now measures otherwise refuses the job."""
    old = tmp_path / "old"
    shutil.copytree(current_sweep, old)
    sweep = SweepFolder(old)
    hashes = [job["config_hash"] for job in json.loads(sweep.jobs_file.read_text())]
    for k, config_hash in enumerate(hashes):
        path = sweep.job(config_hash).result_file
        result = json.loads(path.read_text())
        result["final"].pop("uncertainty_curves")
        if k == 1:  # as other code would have measured it
            result["final"]["uncertainty"]["nll"] += 0.5
        path.write_text(json.dumps(result))
    assert eval_main(["--sweep", str(old)]) == 1  # one refused
    out = capsys.readouterr().out
    assert "1 filled, 0 already current, 1 refused" in out and "differs from the recorded one (nll" in out
    kept = json.loads(sweep.job(hashes[0]).result_file.read_text())["final"]
    truth = json.loads(SweepFolder(current_sweep).job(hashes[0]).result_file.read_text())["final"]
    assert kept["uncertainty_curves"]["mae"]["by_uncertainty"] == pytest.approx(
        truth["uncertainty_curves"]["mae"]["by_uncertainty"], rel=1e-6, abs=1e-12)
    assert kept["uncertainty"] == pytest.approx(truth["uncertainty"], rel=1e-6)
    assert "uncertainty_curves" not in json.loads(sweep.job(hashes[1]).result_file.read_text())["final"]
