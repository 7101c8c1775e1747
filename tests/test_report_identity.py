"""A report never averages unlike things: one code version and one plugin per row, one data
fingerprint per (row, scene); refused with one line naming both identities unless --allow-mixed,
and every report lists the identities behind each row (report.md and runs.csv)."""

import textwrap

import pandas as pd
import pytest
from hydra import compose, initialize_config_dir

from pipeline.report.identity import MixedRowError, check_rows, identity_markdown, mixed_rows
from tests.conftest import SMALL_GENERATED


def _final(method="gopre", scene="bonsai", seed=0, code="aaa", data="f1", **extra):
    return {"kind": "final", "status": "FINISHED", "job_kind": "episode", "sweep": "s", "method": method,
            "dataset": "shared", "scene": scene, "protocol": "goal", "setting": "", "seed": seed,
            "config_hash": f"{method}{scene}{seed}{code}{data}", "psnr": 20.0 + seed, "code_version": code,
            "data_fingerprint": data, **extra}


def test_one_identity_per_row_is_reported_and_listed():
    frame = pd.DataFrame([_final(seed=s) for s in range(3)] + [_final("random", seed=s, code="bbb") for s in range(3)]
                         + [_final(scene="lego", seed=s, data="f2") for s in range(3)])
    assert mixed_rows(frame) == []  # methods may differ in code; scenes differ in data
    check_rows(frame)
    header = identity_markdown(frame)
    assert "| gopre | 6 | aaa | built-in | bonsai: f1; lego: f2 |" in header
    assert "| random | 3 | bbb | built-in | bonsai: f1 |" in header


@pytest.mark.parametrize("change, message", [
    ({"code_version": "ccc"}, r"^row 'gopre' mixes code versions aaa \(2 episode\(s\)\) and ccc \(1\)"),
    ({"data_fingerprint": "f9"}, r"^row 'gopre' on shared/bonsai mixes data fingerprints f1 \(2 episode\(s\)\) and f9 \(1\)"),
    ({"data_fingerprint": None}, r"mixes data fingerprints f1 \(2 episode\(s\)\) and not recorded \(1\)"),
    ({"plugin_sha256": "d" * 64, "plugin_version": "0.2"}, r"mixes plugins built-in \(2 episode\(s\)\) and 0.2 \(source"),
])
def test_a_row_of_unlike_episodes_is_refused_naming_both(change, message):
    rows = [_final(seed=0), _final(seed=1), {**_final(seed=2), **change}]
    frame = pd.DataFrame(rows)
    with pytest.raises(MixedRowError, match=message) as err:
        check_rows(frame)
    assert "\n" not in str(err.value) and "--allow-mixed" in str(err.value)
    check_rows(frame, allow_mixed=True)
    assert "**Mixed rows, reported with `--allow-mixed`:**" in identity_markdown(frame)


def test_settings_are_rows_of_their_own():
    rows = [{**_final(seed=s), "setting": "K=5"} for s in range(2)] + [
        {**_final(seed=s, code="zzz"), "setting": "K=10"} for s in range(2)]
    assert mixed_rows(pd.DataFrame(rows)) == []


PLUGIN = """
    from pipeline.api import timed_selection

    class Lowest:
        name = "lowest"
        def select(self, ctx, count=1):
            return timed_selection(ctx, lambda order: (list(range(count)), [float(OFFSET + i) for i in range(len(order))]))

    OFFSET = {offset}
"""


@pytest.mark.slow
def test_a_plugin_edited_between_runs_is_refused_by_the_report(tmp_path, monkeypatch, capsys):
    """The issue's case: versions of a plugin run into one output folder became one row, their mean."""
    from pipeline.cli.report import main as report_main
    from pipeline.cli.run import CONF_DIR
    from pipeline.experiment.sweep import run_sweep
    monkeypatch.syspath_prepend(str(tmp_path))
    (tmp_path / "conf" / "method").mkdir(parents=True)
    (tmp_path / "conf" / "method" / "mine.yaml").write_text("mine:\n  strategy: my_lowest:Lowest\n")
    for offset in (0, 1):
        (tmp_path / "my_lowest.py").write_text(textwrap.dedent(PLUGIN.format(offset=offset)))
        monkeypatch.delitem(__import__("sys").modules, "my_lowest", raising=False)
        with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
            cfg = compose("config", ["splat=tiny", "dataset=[generated]", *SMALL_GENERATED, "protocol.initial_views=2",
                                     "protocol.budget=3", "protocol.probes=2", "executor=local", "tracking=none",
                                     f"output_dir={tmp_path / 'out'}", f"hydra.searchpath=[file://{tmp_path}/conf]",
                                     "method=[mine]"])
        assert run_sweep(cfg).finished == 1  # the edited plugin is a new job, never "already finished"
    capsys.readouterr()
    assert report_main([str(tmp_path / "out"), "--out", str(tmp_path / "rep"), "--no-images"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("gopre-report: error: row 'mine' mixes plugins no version (source "
                                               "sha256 ")
    assert report_main([str(tmp_path / "out"), "--out", str(tmp_path / "rep"), "--no-images", "--allow-mixed"]) == 0
    runs = pd.read_csv(tmp_path / "rep" / "runs.csv")
    assert runs["plugin_sha256"].nunique() == 2 and set(runs["data_fingerprint"]) == {runs["data_fingerprint"][0]}
    assert runs["data_fingerprint"][0].startswith("generated-")
    assert "## What each row averages" in (tmp_path / "rep" / "report.md").read_text()


@pytest.mark.parametrize("argv,line", [
    (["--paper-only", "nowhere"], "--paper-only goes with --paper"),
    (["--mlflow-uri", "http://x:5000"], "--mlflow-uri and --experiment go together"),
    ([], "give a sweep folder, --results, or --mlflow-uri and --experiment"),
    (["--by-sweep", "nowhere"], "--by-sweep compares sweeps: give two or more sweep folders"),
    (["nowhere", "--benchmark", "b.json"], "--benchmark goes with --results"),
    (["nowhere", "--seeds", "0,x"], "--seeds: expected integers separated by commas, got '0,x'"),
])
def test_report_arguments_that_do_not_go_together_are_refused_before_reading(argv, line, capsys):
    """Each is a usage error (exit 2) naming the arguments, before any folder is read (``nowhere``
    does not exist: reading it first would be a different error)."""
    from pipeline.cli.report import main
    with pytest.raises(SystemExit) as exit_:
        main(argv)
    assert exit_.value.code == 2 and line in capsys.readouterr().err
