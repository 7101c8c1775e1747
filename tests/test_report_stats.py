"""Report statistics against hand-computed values: the curve area, the bootstrap interval, and
paired differences against a reference method (pairs, wins, intervals, missing runs)."""

import numpy as np
import pandas as pd
import pytest

from pipeline.cli.report import main as report_main
from pipeline.report.stats import (bootstrap_interval, curve_area, paired_comparisons, verdict,
                                   with_curve_area)


def row(method, scene, seed, psnr, setting="", kind="final", **extra):
    return {"sweep": "study", "config_hash": f"{method}-{scene}-{seed}-{setting}", "run_id": None,
            "status": "FINISHED", "job_kind": "episode", "kind": kind, "dataset": "blender", "scene": scene,
            "method": method, "strategy": method, "protocol": "global", "seed": seed, "setting": setting,
            "axes": "{}", "psnr": psnr, "ssim": 0.5, "lpips": None, "lpips_status": "off", **extra}


def test_curve_area_is_the_trapezoid_mean_over_the_views_span():
    # views 2, 4, 10 with PSNR 10, 20, 20: (2 * 15 + 6 * 20) / 8 = 18.75, in any order
    assert curve_area(np.array([10, 2, 4]), np.array([20.0, 10.0, 20.0])) == pytest.approx(18.75)
    assert curve_area(np.array([3]), np.array([17.0])) == 17.0


def test_curve_area_joins_each_job_by_its_config_hash():
    final = pd.DataFrame([row("a", "s", 0, 20.0), row("b", "s", 0, 21.0)])
    rounds = pd.DataFrame([row("a", "s", 0, p, kind="round", num_views=n) for n, p in ((2, 10.0), (3, 14.0))] +
                          [row("b", "s", 0, p, kind="round", num_views=n) for n, p in ((2, 11.0), (3, 11.0))])
    assert with_curve_area(final, rounds)["psnr_auc"].tolist() == [12.0, 11.0]


def test_bootstrap_interval_of_the_mean():
    assert bootstrap_interval(np.full(5, 1.5)) == (1.5, 1.5)
    x = np.random.default_rng(3).normal(2.0, 1.0, size=400)
    low, high = bootstrap_interval(x)
    half = 1.96 * x.std(ddof=1) / np.sqrt(x.size)  # the normal-theory interval, for comparison
    assert low < x.mean() < high
    assert (high - low) / 2 == pytest.approx(half, rel=0.1)
    assert bootstrap_interval(x) == bootstrap_interval(x)  # seeded: reproducible
    with pytest.raises(ValueError, match="no values"):
        bootstrap_interval(np.array([]))


@pytest.fixture
def study():
    # gopre vs fisherrf over 2 scenes x 3 seeds; fisherrf lacks (chair, seed 2): that pair is out
    gopre = {("lego", 0): 25.0, ("lego", 1): 26.0, ("lego", 2): 25.5,
             ("chair", 0): 24.0, ("chair", 1): 24.0, ("chair", 2): 23.0}
    other = {("lego", 0): 24.0, ("lego", 1): 26.5, ("lego", 2): 25.5,
             ("chair", 0): 22.0, ("chair", 1): 23.0}
    rows = [row("gopre", s, k, v) for (s, k), v in gopre.items()]
    rows += [row("fisherrf", s, k, v) for (s, k), v in other.items()]
    rows.append({**row("fisherrf", "chair", 2, None), "status": "FAILED"})
    return pd.DataFrame(rows)


def test_paired_comparison_counts_pairs_wins_losses_ties(study):
    final = study[study["status"] == "FINISHED"]
    (c,) = paired_comparisons(final, "gopre", "psnr")
    diffs = np.array([24 - 25, 26.5 - 26, 0.0, 22 - 24, 23 - 24])  # fisherrf - gopre, 5 pairs
    assert (c.method, c.reference, c.n) == ("fisherrf", "gopre", 5)
    assert c.mean_difference == pytest.approx(diffs.mean())
    assert (c.wins, c.losses, c.ties) == (1, 3, 1)
    assert c.low <= diffs.mean() <= c.high and c.low >= diffs.min() and c.high <= diffs.max()
    assert verdict(c) in ("gopre better", "no clear difference")
    reverse = paired_comparisons(final.assign(method=final["method"].replace(
        {"gopre": "x", "fisherrf": "gopre"}).replace({"x": "fisherrf"})), "fisherrf", "psnr")[0]
    assert reverse.mean_difference == pytest.approx(diffs.mean())  # same numbers, names swapped


def test_verdict_needs_an_interval_that_excludes_zero(study):
    final = study[study["status"] == "FINISHED"]
    better = final.assign(psnr=np.where(final["method"] == "fisherrf", final["psnr"] + 5, final["psnr"]))
    (c,) = paired_comparisons(better, "gopre", "psnr")
    assert c.low > 0 and verdict(c) == "fisherrf better"
    with pytest.raises(ValueError, match="reference method 'popgs' has no finished runs"):
        paired_comparisons(final, "popgs", "psnr")


def test_report_cli_writes_paired_tables_against_the_chosen_reference(study, tmp_path, capsys):
    rounds = [row(r["method"], r["scene"], r["seed"], r["psnr"] - 3 + d, kind="round", num_views=n)
              for r in study[study["status"] == "FINISHED"].to_dict("records") for n, d in ((2, 0.0), (3, 2.0))]
    path = tmp_path / "records.parquet"
    pd.concat([study, pd.DataFrame(rounds)]).to_parquet(path)
    assert report_main([str(path), "--out", str(tmp_path / "out")]) == 0
    table = (tmp_path / "out" / "table.md").read_text()
    assert "paired differences against gopre" in table
    line = next(x for x in table.splitlines() if x.startswith("| fisherrf | 5 |"))
    assert "| -0.70 [" in line and "| 1/3/1 |" in line  # mean of -1, 0.5, 0, -2, -1
    assert "\\begin{tabular}" in (tmp_path / "out" / "table.tex").read_text()
    assert report_main([str(path), "--out", str(tmp_path / "o2"), "--reference", "fisherrf"]) == 0
    assert "paired differences against fisherrf" in (tmp_path / "o2" / "table.md").read_text()
    assert report_main([str(path), "--out", str(tmp_path / "o4"), "--seeds", "0,1"]) == 0
    line = next(x for x in (tmp_path / "o4" / "table.md").read_text().splitlines() if x.startswith("| fisherrf | 4 |"))
    assert "4 pair(s): too few for a verdict" in line  # seed 2's pair left out
    capsys.readouterr()
    assert report_main([str(path), "--out", str(tmp_path / "o3"), "--reference", "nosuch"]) == 1
    assert "reference method 'nosuch' did not run" in capsys.readouterr().err


def test_sweeps_run_seed_by_seed_so_an_early_stop_leaves_complete_pairs():
    from pipeline.experiment.sweep import execution_order
    from types import SimpleNamespace
    jobs = [SimpleNamespace(method=m, seed=s, index=i) for i, (m, s) in
            enumerate((m, s) for m in ("gopre", "random") for s in (0, 1, 2))]
    order = [(j.seed, j.method) for j in execution_order(jobs)]
    assert order == [(0, "gopre"), (0, "random"), (1, "gopre"), (1, "random"), (2, "gopre"), (2, "random")]


def test_no_verdict_from_fewer_than_five_pairs(study):
    final = study[(study["status"] == "FINISHED") & (study["seed"] < 2)]  # 4 pairs
    better = final.assign(psnr=np.where(final["method"] == "fisherrf", final["psnr"] + 5, final["psnr"]))
    (c,) = paired_comparisons(better, "gopre", "psnr")
    assert c.n == 4 and c.low > 0 and verdict(c) == "4 pair(s): too few for a verdict"


def test_wilcoxon_p_is_the_exact_signed_rank_probability():
    from pipeline.report.stats import wilcoxon_p
    # all five differences positive: W- = 0 is the most extreme of 2^5 sign patterns, both tails
    assert wilcoxon_p(np.array([1.0, 2.0, 3.0, 4.0, 5.0])) == pytest.approx(2 / 32)
    # one of the smallest flipped: W- = 1 has 2 patterns (W- in {0, 1}) per tail
    assert wilcoxon_p(np.array([-1.0, 2.0, 3.0, 4.0, 5.0])) == pytest.approx(2 * 2 / 32)
    assert wilcoxon_p(np.array([0.0, 0.0])) is None  # no non-zero difference: no test
    assert wilcoxon_p(np.array([0.0, 1.0, 2.0, 3.0, 4.0, 5.0])) == pytest.approx(2 / 32)  # zeros dropped


def test_the_interval_is_bca_as_written_out_by_hand():
    """Efron's BCa, computed here from its definition (bias correction z0 from the bootstrap
    distribution, acceleration from the jackknife), on a skewed sample where it differs from the
    percentile interval by far more than the Monte-Carlo noise of either."""
    from scipy.stats import norm
    x = np.random.default_rng(0).exponential(1.0, size=20)
    boot = x[np.random.default_rng(5).integers(0, x.size, (200_000, x.size))].mean(1)
    z0 = norm.ppf((boot < x.mean()).mean())
    jack = np.array([np.delete(x, i).mean() for i in range(x.size)])
    dev = jack.mean() - jack
    a = (dev ** 3).sum() / (6 * (dev ** 2).sum() ** 1.5)
    by_hand = [np.quantile(boot, norm.cdf(z0 + (z0 + z) / (1 - a * (z0 + z))))
               for z in (norm.ppf(0.025), norm.ppf(0.975))]
    percentile = np.quantile(boot, [0.025, 0.975])
    assert abs(by_hand[0] - percentile[0]) > 0.05  # the two rules really differ here
    assert bootstrap_interval(x) == pytest.approx(by_hand, abs=0.02)


def test_one_pair_prints_no_interval(study):
    """One pair has no interval: it printed +0.31 [+0.31, +0.31] as if it were exact."""
    from pipeline.report.paper import Gap
    from pipeline.report.tables import _paired_cells
    final = study[(study["status"] == "FINISHED") & (study["seed"] == 0) & (study["dataset"] == study["dataset"].iloc[0])]
    final = final[final["scene"] == final["scene"].iloc[0]]
    (c,) = paired_comparisons(final, "gopre", "psnr")
    assert c.n == 1
    cell = _paired_cells(c, "psnr")[0]
    assert cell.endswith(" [n/a]") and cell.count("[") == 1, cell
    assert Gap(1, 0.31, 0.31, 0.31).text() == "+0.31 dB [n/a], n = 1"
    assert Gap(2, 0.31, 0.1, 0.5).text() == "+0.31 dB [+0.10, +0.50], n = 2"
