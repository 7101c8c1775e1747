"""The report of searches off the pool (issue 28): counted by hand on fixture records."""

import json

import numpy as np
import pandas as pd
import pytest

from pipeline.report import search
from pipeline.report.figures import search_landscape
from pipeline.report.report import make_report


def row(method, strategy, seed, kind, setting="protocol.kind=global", **extra):
    return {"sweep": "fixture", "config_hash": f"{method}-{seed}-{setting}", "run_id": None, "status": "FINISHED",
            "job_kind": "episode", "kind": kind, "dataset": "generated", "scene": "generated", "method": method,
            "strategy": strategy, "protocol": "global", "seed": seed, "setting": setting, "axes": "{}", **extra}


def searched_round(method, strategy, seed, views, taken, score, pool_best, **extra):
    return row(method, strategy, seed, "round", num_views=views, psnr=10.0 + views, search_taken=taken,
               world="twin" if method == "fisherrf_search" else "generated",
               search_score=score, search_best_pool_score=pool_best, search_best_start_score=pool_best, **extra)


@pytest.fixture
def frame():
    rows = []
    for seed in range(5):
        # gopre (costs > 0) and its search; fisherrf (costs = negated gains < 0) and its search
        rows.append(row("gopre", "gopre", seed, "final", psnr=20.0 + seed, selection_cpu_seconds=2.0,
                        selection_seconds=3.0))
        rows.append(row("gopre_search", "gopre", seed, "final", psnr=20.5 + seed, selection_cpu_seconds=5.0,
                        selection_seconds=7.0))
        rows.append(row("fisherrf", "fisherrf", seed, "final", psnr=19.0 + seed, selection_cpu_seconds=2.5))
        rows.append(row("fisherrf_search", "fisherrf", seed, "final", psnr=18.0 + seed,
                        selection_cpu_seconds=4.0))
        rows.append(row("random", "random", seed, "final", psnr=17.0))
        for views in (2, 3):
            rows.append(row("gopre", "gopre", seed, "round", num_views=views, psnr=10.0 + views))
            rows.append(row("fisherrf", "fisherrf", seed, "round", num_views=views, psnr=10.0 + views))
        # gopre_search: round 2 captured with cost 98 against the pool's 100 (2 %), round 3 pool
        rows.append(searched_round("gopre_search", "gopre", seed, 2, "search", 98.0, 100.0))
        rows.append(searched_round("gopre_search", "gopre", seed, 3, "pool", 101.0, 100.0))
        # fisherrf_search: gains 50 -> cost -55 against the pool's -50 (10 % below), both rounds
        rows.append(searched_round("fisherrf_search", "fisherrf", seed, 2, "search", -55.0, -50.0))
        rows.append(searched_round("fisherrf_search", "fisherrf", seed, 3, "search", -55.0, -50.0))
    return pd.DataFrame(rows)


def cells(markdown, method):
    line = next(r for r in markdown.splitlines() if f"| {method} |" in r)
    return [c.strip() for c in line.strip("|").split("|")]


def test_the_search_table_counts_captured_rounds_and_the_gain_over_the_pool(frame):
    table = search.search_table(frame)
    gopre = cells(table, "gopre_search")
    assert gopre[3:] == ["5", "10", "5 (50%)", "2.00%", "0"]  # episodes, rounds, captured, (100 - 98) / 100
    fisher = cells(table, "fisherrf_search")
    assert fisher[3:] == ["5", "10", "10 (100%)", "10.00%", "0"]  # a negated gain: |-50| in the denominator
    assert "| gopre |" not in table  # only methods that searched

    control = pd.DataFrame([searched_round("gopre_pool_captured", "gopre", seed, views, "pool_captured", None, None)
                            for seed in range(2) for views in (2, 3)])
    assert cells(search.search_table(control), "gopre_pool_captured")[3:] == ["2", "4", "0 (0%)", "—", "4"]


def test_selection_time_is_listed_for_every_method(frame):
    table = search.selection_time_table(frame)
    assert cells(table, "gopre")[3:] == ["2.00", "3.00"]
    assert cells(table, "gopre_search")[3:] == ["5.00", "7.00"]
    assert cells(table, "random")[3:] == ["—", "—"]


def test_each_searched_method_is_paired_with_its_pool_twin(frame):
    assert search.pool_twin(frame, "gopre_search") == "gopre"
    assert search.pool_twin(frame, "fisherrf_search") == "fisherrf"
    tables = search.twin_tables(frame, "fixture")
    by_twin = {t.reference: t for t in tables}
    assert set(by_twin) == {"gopre", "fisherrf"}
    assert by_twin["gopre"].rows["gopre_search"]["psnr"].mean_difference == pytest.approx(0.5)
    assert by_twin["fisherrf"].rows["fisherrf_search"]["psnr"].mean_difference == pytest.approx(-1.0)
    assert by_twin["fisherrf"].rows["fisherrf_search"]["psnr"].n == 5
    assert {t.reference for t in search.twin_tables(frame, "fixture", skip="gopre")} == {"fisherrf"}


def test_no_twin_when_two_pool_methods_share_the_strategy(frame):
    extra = frame[frame["method"] == "gopre"].assign(method="gopre_identity")
    both = pd.concat([frame, extra], ignore_index=True)
    assert search.pool_twin(both, "gopre_search") is None


def test_a_landscape_is_read_from_a_result_and_drawn_relative_to_the_pool(tmp_path):
    result = {"rounds": [
        {"round": 0, "search": {"best_pool_score": 10.0, "taken": "search",
                                "evaluated": [[10.0, 20.0, 3.0, 11.0], [30.0, 25.0, 3.0, 9.0], [50.0, 5.0, 3.2, 12.0]]}},
        {"round": 1},  # the final round: no search
        {"round": 2, "search": {"best_pool_score": -4.0, "taken": "pool",
                                "evaluated": [[0.0, 10.0, 3.0, -3.0], [5.0, 15.0, 3.0, -2.0]]}}]}
    rounds = search.landscapes(result)
    assert [r.round for r in rounds] == [0, 2]
    assert rounds[0].best.tolist() == [30.0, 25.0, 3.0]
    np.testing.assert_allclose(rounds[0].relative_costs(), [0.1, -0.1, 0.2])
    np.testing.assert_allclose(rounds[1].relative_costs(), [0.25, 0.5])  # (-3 - -4) / |-4|
    drawn = search_landscape(rounds, tmp_path / "l.png", "fixture")
    assert drawn[0] == ([10.0, -10.0, 20.0], "search") and drawn[2][1] == "pool"
    assert (tmp_path / "l.png").exists() and (tmp_path / "l.pdf").exists()


def test_the_report_of_a_sweep_that_searched_has_its_section(frame, tmp_path):
    sweep = tmp_path / "sweep"
    job = sweep / "jobs" / "gopre_search-0-protocol.kind=global" / "artifacts"
    job.mkdir(parents=True)
    job.joinpath("result.json").write_text(json.dumps({"rounds": [
        {"round": 0, "search": {"best_pool_score": 100.0, "taken": "search",
                                "evaluated": [[0.0, 10.0, 3.0, 98.0], [5.0, 15.0, 3.0, 101.0]]}}]}))
    frame.to_parquet(sweep / "records.parquet")
    report = make_report(sweep, tmp_path / "out")
    text = (tmp_path / "out" / "report.md").read_text()
    assert "## Beyond the pool" in text and (tmp_path / "out" / "search.md").exists()
    assert search.WORLD_NOTES["twin"] in text and search.WORLD_NOTES["generated"] in text
    assert "search_landscape_0.png" in report["figures"]
    assert "searched off the pool against the pool (fisherrf)" in report["tables"]


def test_a_searched_method_is_also_paired_with_the_capture_control(frame):
    control = []
    for seed in range(5):
        control.append(row("gopre_pool_captured", "gopre", seed, "final", psnr=20.2 + seed))
        control += [searched_round("gopre_pool_captured", "gopre", seed, views, "pool_captured", None, None)
                    for views in (2, 3)]
    both = pd.concat([frame, pd.DataFrame(control)], ignore_index=True)
    assert search.capture_control(both, "gopre_search") == "gopre_pool_captured"
    assert search.capture_control(both, "fisherrf_search") is None  # another strategy
    assert search.pool_twin(both, "gopre_search") == "gopre"  # the control searched (it is no pool twin)
    tables = {t.reference: t for t in search.twin_tables(both, "fixture", skip="gopre")}
    vs_control = tables["gopre_pool_captured"]
    assert "simulator's images" in vs_control.title and set(vs_control.rows) == {"gopre_search"}
    assert vs_control.rows["gopre_search"]["psnr"].mean_difference == pytest.approx(0.3)
