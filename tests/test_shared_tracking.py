"""Two output folders on one tracking store: each gets its own complete records (a run another
folder finished is not this folder's result), and each relaunch skips only its own."""

import pytest
from hydra import compose, initialize_config_dir

from pipeline.cli.run import CONF_DIR
from pipeline.experiment.records import RecordsFile
from pipeline.experiment.sweep import run_sweep
from tests.conftest import SMALL_GENERATED


def _cfg(out, store, more=()):
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        return compose("config", ["splat=tiny", "dataset=[generated]", *SMALL_GENERATED, "protocol.initial_views=2",
                                  "protocol.budget=3",
                                  "protocol.probes=2", "executor=local", "tracking=mlflow", f"tracking.uri={store}",
                                  "method=[random]", "seeds=[0]", "job.round_images=0", f"output_dir={out}", *more])


@pytest.mark.slow
def test_a_new_folder_on_a_shared_store_runs_its_own_jobs(tmp_path):
    store = f"sqlite:///{tmp_path / 'server.db'}"  # one store for both folders, as a shared server
    first = run_sweep(_cfg(tmp_path / "a", store))
    assert first.finished == 1 and first.skipped == 0
    second = run_sweep(_cfg(tmp_path / "b", store))  # the same config, another folder
    assert second.skipped == 0 and second.finished == 1
    assert len(RecordsFile(tmp_path / "b").frame.query("kind == 'final'")) == 1
    assert (tmp_path / "b" / "jobs").is_dir()
    assert run_sweep(_cfg(tmp_path / "a", store)).skipped == 1  # each folder still resumes its own


@pytest.mark.slow
def test_another_folders_finished_jobs_are_taken_only_when_named(tmp_path):
    """reuse_from copies the named folder's finished jobs in (job folder, then records rows with
    reused_from), runs only the rest, and the store gets them as runs of this folder."""
    from mlflow import MlflowClient

    from pipeline.experiment.episode_settings import ConfigError
    from pipeline.experiment.layout import SweepFolder
    store = f"sqlite:///{tmp_path / 'server.db'}"
    assert run_sweep(_cfg(tmp_path / "a", store)).finished == 1
    (done,) = RecordsFile(tmp_path / "a").finished_hashes()
    cfg = _cfg(tmp_path / "c", store, ["method=[random,coverage]", f"reuse_from=[{tmp_path / 'a'}]"])
    summary = run_sweep(cfg)
    assert summary.finished == 1 and summary.skipped == 1  # coverage ran; random was taken
    frame = RecordsFile(tmp_path / "c").frame
    taken, ran = frame[frame["config_hash"] == done], frame[frame["config_hash"] != done]
    theirs = RecordsFile(tmp_path / "a").frame
    assert set(taken["reused_from"]) == {str((tmp_path / "a").resolve())} and ran["reused_from"].isna().all()
    final = lambda f: f.query("kind == 'final'").iloc[0]  # noqa: E731
    assert final(taken)["psnr"] == final(theirs)["psnr"] and len(taken) == len(theirs)
    job = SweepFolder(tmp_path / "c").job(done)
    assert job.result_file.read_bytes() == SweepFolder(tmp_path / "a").job(done).result_file.read_bytes()
    assert not job.checkpoint_dir.exists()
    client = MlflowClient(store)
    runs = client.search_runs([e.experiment_id for e in client.search_experiments()],
                              f"tags.config_hash = '{done}' and attributes.status = 'FINISHED'")
    assert len({r.data.tags.get("output_dir") for r in runs}) == 2  # a's run and c's replayed one
    with pytest.raises(ConfigError, match="reuse_from: .*nowhere has no records.parquet"):
        run_sweep(_cfg(tmp_path / "d", store, [f"reuse_from=[{tmp_path / 'nowhere'}]"]))
    with pytest.raises(ConfigError, match="reuse_from: expected a list of output folders"):
        run_sweep(_cfg(tmp_path / "d", store, ["reuse_from=3"]))


def test_a_copy_that_fails_midway_leaves_no_rows_and_a_named_folder_must_be_an_output_folder(tmp_path, monkeypatch):
    """reuse_finished without a sweep: every job folder is copied before any row is written, so a
    copy that fails part way leaves this folder's records as they were."""
    import shutil

    import pandas as pd

    from pipeline.experiment import reuse
    from pipeline.experiment.episode_settings import ConfigError
    from pipeline.experiment.layout import SweepFolder
    source, here = tmp_path / "a", tmp_path / "b"
    rows = []
    for h in ("h1", "h2"):
        job = SweepFolder(source).job(h)
        job.artifacts.mkdir(parents=True)
        job.result_file.write_text("{}")
        (job.checkpoint_dir).mkdir()
        (job.checkpoint_file).write_text("resume state")
        rows.append({"config_hash": h, "kind": "final", "status": "FINISHED", "code_version": "abc", "psnr": 20.0})
    pd.DataFrame(rows).to_parquet(SweepFolder(source).records_file, index=False)
    jobs = [type("J", (), {"config_hash": h})() for h in ("h1", "h2", "h3")]
    copied = []
    real = shutil.copytree

    def copy_then_fail(src, dst, *args, **kw):
        if args:  # copytree's own recursion into a subfolder
            return real(src, dst, *args, **kw)
        if copied:
            raise OSError("disk full")
        copied.append(src)
        return real(src, dst, **kw)
    monkeypatch.setattr(reuse.shutil, "copytree", copy_then_fail)
    records = RecordsFile(here)
    with pytest.raises(OSError, match="disk full"):
        reuse.reuse_finished(jobs, [source], here, records)
    assert RecordsFile(here).frame.empty and records.frame.empty
    monkeypatch.setattr(reuse.shutil, "copytree", real)
    (taken,) = reuse.reuse_finished(jobs, [source], here, records)
    assert taken.hashes == ["h1", "h2"] and sorted(RecordsFile(here).finished_hashes()) == ["h1", "h2"]
    assert not SweepFolder(here).job("h1").checkpoint_dir.exists()  # the resume state stays behind
    assert reuse.reuse_finished(jobs, [source], here, records) == []  # finished here now: nothing to take
    with pytest.raises(ConfigError, match="this sweep's own output_dir"):
        reuse.reuse_finished(jobs, [here], here, records)
