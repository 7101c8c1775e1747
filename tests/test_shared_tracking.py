"""Two output folders on one tracking store: each gets its own complete records (a run another
folder finished is not this folder's result), and each relaunch skips only its own."""

import pytest
from hydra import compose, initialize_config_dir

from pipeline.cli.run import CONF_DIR
from pipeline.experiment.records import RecordsFile
from pipeline.experiment.sweep import run_sweep


def _cfg(out, store):
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        return compose("config", ["splat=tiny", "dataset=[generated]", "protocol.initial_views=2", "protocol.budget=3",
                                  "protocol.probes=2", "executor=local", "tracking=mlflow", f"tracking.uri={store}",
                                  "method=[random]", "seeds=[0]", "job.round_images=0", f"output_dir={out}"])


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
