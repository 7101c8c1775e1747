"""Effect size and the seeds a paired test needs, against published G*Power values and a
simulation of the t-test itself."""

import math

import numpy as np
import pytest
from scipy.stats import ttest_rel

from pipeline.report.power import effect_size, paired_t_power, seeds_needed


def test_effect_size_by_hand():
    assert effect_size([1.0, 2.0, 3.0]) == pytest.approx(2.0 / 1.0)  # mean 2, sd (n-1) 1
    assert effect_size([-0.5, 0.5]) == pytest.approx(0.0)
    assert effect_size([1.0]) is None and effect_size([0.3, 0.3, 0.3]) is None


@pytest.mark.parametrize("dz, n", [(0.5, 34), (0.8, 15), (1.0, 10), (0.2, 199)])
def test_seeds_needed_are_g_powers(dz, n):
    """G*Power 3.1, t-test, matched pairs, two-tailed, alpha 0.05, power 0.80: total sample size."""
    assert seeds_needed(dz) == n and seeds_needed(-dz) == n
    assert paired_t_power(dz, n) >= 0.8 > paired_t_power(dz, n - 1)


@pytest.mark.parametrize("dz, n", [(0.7, 12), (2.0, 3)])  # 3 pairs: the degrees of freedom matter most
def test_the_power_is_the_t_tests_rejection_rate(dz, n):
    rng = np.random.default_rng(0)
    trials = 20_000
    d = rng.normal(dz, 1.0, (trials, n))
    rejected = np.mean(ttest_rel(d, np.zeros_like(d), axis=1).pvalue < 0.05)
    assert rejected == pytest.approx(paired_t_power(dz, n), abs=0.01)


def test_no_effect_needs_no_finite_number_of_seeds():
    assert seeds_needed(None) is None and seeds_needed(0.0) is None and seeds_needed(0.01) is None
    assert math.isclose(paired_t_power(0.0, 50), 0.05, abs_tol=1e-9)


def test_the_paired_table_shows_the_effect_and_the_seeds_it_needs():
    import pandas as pd

    from pipeline.report.stats import paired_comparisons
    from pipeline.report.tables import PairedTable, paired_to_markdown
    gopre = [20.0, 21.0, 22.0, 20.5]
    other = [19.0, 20.5, 20.0, 20.4]  # differences +1.0 +0.5 +2.0 +0.1
    rows = [{"method": m, "dataset": "d", "scene": "s", "seed": k, "setting": "", "psnr": v}
            for m, values in (("gopre", gopre), ("other", other)) for k, v in enumerate(values)]
    (c,) = paired_comparisons(pd.DataFrame(rows), "other", "psnr")
    d = np.array(gopre) - np.array(other)
    assert c.effect_size == pytest.approx(d.mean() / d.std(ddof=1)) and c.seeds_needed == seeds_needed(c.effect_size)
    text = paired_to_markdown(PairedTable("t", "other", ["psnr"], {"gopre": {"psnr": c}}))
    assert "final PSNR d_z (seeds for 80% power)" in text
    assert f"| {c.effect_size:+.2f} ({c.seeds_needed}) |" in text
