"""``SweepResults``: a sweep folder read without torch, giving what the writers wrote (records,
each episode typed, the portable result, the model file, the jobs); absent things are None or one
error naming the folder."""

import json
import subprocess
import sys
from pathlib import Path

import jsonschema
import pytest
from hydra import compose, initialize_config_dir

from pipeline.cli.run import CONF_DIR
from pipeline.experiment.records import RecordsFile
from pipeline.experiment.sweep import run_sweep
from pipeline.interchange.documents import schema
from pipeline.interchange.results import EpisodeResult
from pipeline.interchange.sweep_results import SweepResults

ROOT = Path(__file__).resolve().parents[1]
TINY = ["experiment=debug", "splat=tiny", "splat.iterations=40", "dataset.generated.generate.size=32",
        "dataset.generated.generate.n_train=16", "dataset.generated.generate.n_test=8",
        "protocol.initial_views=2", "protocol.budget=4", "protocol.probes=2", "executor=local", "tracking=none"]


@pytest.fixture(scope="module")
def sweep(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("results") / "sweep"
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        cfg = compose("config", [*TINY, "method=[random,coverage]", "seeds=[0]", f"output_dir={out}"])
    assert run_sweep(cfg).finished == 2
    return out


def test_the_reader_gives_what_the_sweep_wrote(sweep):
    results = SweepResults(sweep)
    stored = RecordsFile(sweep).frame
    finals = results.finished()
    assert sorted(finals["config_hash"]) == sorted(stored[stored["kind"] == "final"]["config_hash"])
    assert [j["config_hash"] for j in results.job_configs()] == list(
        json.loads((sweep / "jobs.json").read_text())[k]["config_hash"] for k in range(2))
    for row in finals.itertuples():
        episode = results.episode(row.config_hash)
        assert isinstance(episode, EpisodeResult) and episode.gaussians is None
        assert episode.final.psnr == pytest.approx(row.psnr) and episode.strategy == row.strategy
        assert json.loads(json.dumps(episode.to_dict())) == results.episode_data(row.config_hash)  # score keys: text
        document = results.result_document(row.config_hash)
        jsonschema.validate(document, schema("result"))
        assert document["config_hash"] == row.config_hash
        assert [r["selected"] for r in document["rounds"][:-1]] == [r.selected for r in episode.rounds[:-1]]
        assert results.model_file(row.config_hash).stat().st_size > 0


def test_what_is_absent_is_none_or_one_error_naming_the_folder(tmp_path, sweep):
    results = SweepResults(sweep)
    assert results.episode("0" * 16) is None and results.result_document("0" * 16) is None
    empty = SweepResults(tmp_path / "nothing")
    assert empty.finished().empty and empty.records.empty
    with pytest.raises(ValueError, match=f"{tmp_path / 'nothing'}: no jobs.json"):
        empty.job_configs()


def test_reading_a_sweep_imports_no_torch(sweep):
    code = ("import sys; from pipeline.interchange.sweep_results import SweepResults; "
            f"r = SweepResults({str(sweep)!r}); h = r.finished()['config_hash'].iloc[0]; "
            "e = r.episode(h); d = r.result_document(h); "
            "print(e.final.psnr > 0, d['final']['psnr'] == e.final.psnr, 'torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["True", "True", "False"], out.stdout + out.stderr
