"""The round-to-round falls of the curve (pipeline/report/falls.py) against a brute force over
every pair of rounds, and sweeps compared as settings (gopre-report A B --by-sweep): the paired
differences of each method's settings against hand-computed ones."""

import numpy as np
import pandas as pd
import pytest

from pipeline.report.falls import episode_falls, falls_markdown, worst_fall
from pipeline.report.report import combine_records, make_report


def brute_worst_fall(views, psnr):
    """Every consecutive pair, the largest psnr[i] - psnr[i + 1] if any is positive."""
    best = (0.0, None, None)
    for i in range(len(psnr) - 1):
        drop = psnr[i] - psnr[i + 1]
        if drop > best[0]:
            best = (drop, views[i], views[i + 1])
    return best


@pytest.mark.parametrize("seed", range(40))
def test_the_worst_fall_is_the_largest_drop_between_consecutive_rounds(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 12))
    views = np.arange(4, 4 + n)
    psnr = 15 + np.cumsum(rng.normal(0.3, 0.8, n))
    fall = worst_fall(views, psnr)
    want = brute_worst_fall(list(views), list(psnr))
    assert fall.fall_db == pytest.approx(want[0], abs=0)
    assert (fall.from_views, fall.to_views) == want[1:]


def test_a_curve_that_never_goes_down_has_no_fall():
    flat_then_up = worst_fall(np.array([2, 3, 4]), np.array([10.0, 10.0, 12.0]))
    assert (flat_then_up.fall_db, flat_then_up.from_views, flat_then_up.to_views) == (0.0, None, None)
    assert worst_fall(np.array([2]), np.array([10.0])).from_views is None


def round_rows(method, seed, curve, setting="", sweep="s", scene="bonsai", status="FINISHED"):
    """A job's round rows (num_views 4, 5, ...) and its final row, listed in a shuffled order."""
    job = f"{sweep}-{method}-{scene}-{seed}-{setting}"
    base = {"sweep": sweep, "config_hash": job, "status": status, "job_kind": "episode", "dataset": "d",
            "scene": scene, "method": method, "strategy": method, "protocol": "goal", "seed": seed,
            "setting": setting, "axes": "{}", "run_id": None, "ssim": 0.5, "lpips": None}
    rows = [{**base, "kind": "round", "num_views": 4 + k, "iteration": 100.0 * (k + 1), "psnr": p}
            for k, p in enumerate(curve)]
    rows = rows[::-1]  # records list rounds as they finish; the falls read them in training order
    return rows + [{**base, "kind": "final", "num_views": 3 + len(curve), "iteration": np.nan,
                    "psnr": curve[-1] + 0.5}]


def test_each_finished_episode_gets_its_worst_fall_in_training_order_and_its_final_psnr():
    frame = pd.DataFrame(round_rows("a", 0, [15.0, 16.0, 14.5, 15.0, 14.9])
                         + round_rows("a", 1, [15.0, 15.5, 16.0])
                         + round_rows("b", 0, [15.0, 13.0], status="FAILED"))
    falls = episode_falls(frame).set_index("seed")
    assert list(falls.index) == [0, 1]  # the failed job is not an episode of the report
    assert falls.loc[0, "worst_fall_db"] == pytest.approx(1.5)
    assert (falls.loc[0, "from_views"], falls.loc[0, "to_views"]) == (5, 6)
    assert falls.loc[0, "final_psnr"] == pytest.approx(15.4)
    assert falls.loc[1, "worst_fall_db"] == 0.0


def test_the_falls_table_names_the_worst_episode_and_counts_those_above_the_threshold():
    frame = pd.DataFrame(round_rows("a", 0, [15.0, 13.8, 14.0]) + round_rows("a", 1, [15.0, 14.5])
                         + round_rows("a", 2, [15.0, 13.9]) + round_rows("b", 0, [15.0, 16.0]))
    text = falls_markdown(episode_falls(frame))
    row_a = next(line for line in text.splitlines() if line.startswith("| a |"))
    assert "1.20 (seed 0, 4 → 5)" in row_a and "2 of 3" in row_a
    row_b = next(line for line in text.splitlines() if line.startswith("| b |"))
    assert "never falls" in row_b and "0 of 1" in row_b


def test_sweeps_compared_by_sweep_are_settings_paired_method_by_method(tmp_path):
    """Two sweeps of the same episodes (the paper's reset, and none): each a setting named after
    its sweep; each method's second sweep paired against its first over the seeds, by hand."""
    paper, variant = [], []
    finals = {("a", s): (20.0 + s, 20.5 + 2 * s) for s in range(5)}
    finals.update({("b", s): (18.0, 17.0 + 0.1 * s) for s in range(5)})
    for (method, seed), (p, v) in finals.items():
        paper += round_rows(method, seed, [15.0, 13.5, p - 0.5], sweep="paper")
        variant += round_rows(method, seed, [15.0, 15.2, v - 0.5], sweep="noreset")
    for name, rows in (("paper", paper), ("noreset", variant)):
        (tmp_path / name).mkdir()
        pd.DataFrame(rows).assign(job_index=0).to_parquet(tmp_path / name / "records.parquet")
    with pytest.raises(ValueError, match="more than one of the sweeps"):
        combine_records([tmp_path / "paper", tmp_path / "noreset"])  # as one table: the same episodes twice
    frame = combine_records([tmp_path / "paper", tmp_path / "noreset"], by_sweep=True)
    assert set(frame["setting"]) == {"paper", "noreset"}
    summary = make_report(tmp_path / "paper", tmp_path / "out", frame, baseline_setting="paper")
    table = next(t for t in summary["tables"].split("### ") if "each setting against paper" in t)
    row_a = next(line for line in table.splitlines() if line.startswith("| a: noreset |"))
    row_b = next(line for line in table.splitlines() if line.startswith("| b: noreset |"))
    for method, row in (("a", row_a), ("b", row_b)):
        diffs = np.array([v - p for (m, _), (p, v) in finals.items() if m == method])
        wins, losses = int((diffs > 0).sum()), int((diffs < 0).sum())
        assert row.split(" | ")[2].startswith(f"{diffs.mean():+.2f} [")
        assert f"| {wins}/{losses}/{5 - wins - losses} |" in row
    assert "| 5/0/0 |" in row_a and "| 0/5/0 |" in row_b  # the fixture's two directions
    falls = pd.read_csv(tmp_path / "out" / "falls.csv")
    assert set(falls[falls["setting"] == "paper"]["worst_fall_db"].round(6)) == {1.5}
    assert (falls[falls["setting"] == "noreset"]["worst_fall_db"] == 0).all()
    assert "## Round-to-round falls of the curve" in (tmp_path / "out" / "report.md").read_text()


def test_sweeps_of_one_name_cannot_be_told_apart_and_say_so(tmp_path):
    for name in ("x", "y"):
        (tmp_path / name).mkdir()
        pd.DataFrame(round_rows("a", 0, [15.0, 16.0], sweep="same")).assign(job_index=0).to_parquet(
            tmp_path / name / "records.parquet")
    with pytest.raises(ValueError, match=r"y and .*x are both sweep 'same'.*name="):
        combine_records([tmp_path / "x", tmp_path / "y"], by_sweep=True)


def test_the_cli_compares_sweeps_against_the_first_and_refuses_one_sweep(tmp_path, capsys):
    from pipeline.cli.report import main
    for name, bump in (("first", 0.0), ("second", 1.0)):
        (tmp_path / name).mkdir()
        rows = [r for s in range(2) for r in round_rows("a", s, [15.0, 16.0 + bump], sweep=name)]
        pd.DataFrame(rows).assign(job_index=0).to_parquet(tmp_path / name / "records.parquet")
    assert main([str(tmp_path / "first"), str(tmp_path / "second"), "--by-sweep",
                 "--out", str(tmp_path / "out")]) == 0
    assert "| a: second | 2 | +1.00" in capsys.readouterr().out
    report = (tmp_path / "out" / "report.md").read_text()  # named after both sweeps, not the first
    assert report.startswith("# Report: first + second\n") and "jobs from sweeps `first`, `second`," in report
    with pytest.raises(SystemExit):
        main([str(tmp_path / "first"), "--by-sweep", "--out", str(tmp_path / "out2")])
    assert "give two or more sweep folders" in capsys.readouterr().err


@pytest.mark.parametrize("with_sweep", [True, False])
def test_the_same_job_in_two_sweeps_keeps_its_own_curve_in_each(tmp_path, with_sweep):
    """The same config under two code versions has one config hash in both sweeps: compared by
    sweep, each keeps its own curve (falls, final PSNR, curve area), not the two merged."""
    old = round_rows("a", 0, [15.0, 13.0, 16.0], sweep="old")
    new = round_rows("a", 0, [15.0, 15.5, 16.5], sweep="new")
    for row in old + new:
        row["config_hash"] = "same-job"
    frame = pd.DataFrame(old + new).assign(setting=lambda f: f["sweep"])
    if not with_sweep:  # one sweep's rows alone, without the sweep column, still read
        frame = pd.DataFrame(old).drop(columns="sweep")
    falls = episode_falls(frame).set_index("setting") if with_sweep else episode_falls(frame)
    if with_sweep:
        assert falls.loc["old", "worst_fall_db"] == pytest.approx(2.0)
        assert falls.loc["new", "worst_fall_db"] == 0.0
        assert falls.loc["new", "final_psnr"] == pytest.approx(17.0)
        from pipeline.report.report import episode_tables
        pooled = episode_tables(frame, "t")[0]  # one method: a row per setting
        areas = {row: pooled.cells[(row, ("", "psnr_auc"))].mean for row in pooled.rows}
        assert areas == {"old": pytest.approx(14.25), "new": pytest.approx(15.625)}  # trapezoids by hand
    else:
        assert falls["worst_fall_db"].tolist() == [pytest.approx(2.0)]
        assert falls["final_psnr"].tolist() == [pytest.approx(16.5)]


def test_a_baseline_without_curves_is_compared_on_final_psnr_alone():
    """Final rows only (no rounds recorded, so no curve area): the settings are still paired on
    final PSNR, not refused."""
    from pipeline.report.report import setting_tables
    rows = [{"method": "a", "setting": s, "dataset": "d", "scene": "x", "seed": seed, "psnr": 20.0 + seed + bump,
             "psnr_auc": np.nan} for seed in range(3) for s, bump in (("base", 0.0), ("other", 0.5))]
    (table,) = setting_tables(pd.DataFrame(rows), "t", ["a"], ["base", "other"], "base")
    assert table.rows["a: other"]["psnr"].mean_difference == pytest.approx(0.5)
    assert "psnr_auc" not in table.rows["a: other"]
