"""tetdose.compare.significance: physics told from noise on synthetic doses with known σ.

Each "run" is the mean of 10 batches of a known field with Gaussian batch noise (5 % per point,
as a Monte Carlo dose's), and its σ the batches' standard error — as tetdose's runs report it.
"""

import numpy as np
import pytest

from tetdose.compare.significance import (
    mean_rel_diff,
    normalised_difference,
    pooled_sigma,
    structure_significance,
    systematic_fit,
)

N, B, REL = 20_000, 10, 0.05
X = np.linspace(-1.0, 1.0, N)
TRUE = 1.0 + 0.5 * np.cos(3.0 * X)  # Gy


def run(seed, true=TRUE):
    """(dose, σ) of one unbiased run: the mean of B noisy batches and its standard error."""
    rng = np.random.default_rng(seed)
    batches = true[None, :] * (1.0 + REL * np.sqrt(B) * rng.standard_normal((B, true.size)))
    return batches.mean(axis=0), batches.std(axis=0, ddof=1) / np.sqrt(B)


@pytest.fixture(scope="module")
def two_runs():
    return run(1), run(2)


def test_two_unbiased_runs_are_statistically_consistent(two_runs):
    (a, sa), (b, sb) = two_runs
    fit, posterior = systematic_fit(a, sa, b, sb)
    assert fit.model == "none" and fit.fraction == 0.0
    assert abs(fit.delta) <= 0.01 and abs(fit.delta) <= 3 * fit.delta_sigma
    assert fit.delta_sigma < 0.002  # 5 % per point over 2e4 points: ~0.05 %
    assert np.nanmax(posterior) == 0.0


def test_a_dose_scaled_by_four_percent_is_found_systematic_everywhere(two_runs):
    (a, sa), (b, sb) = two_runs
    fit, _ = systematic_fit(1.04 * a, 1.04 * sa, b, sb)
    assert fit.model == "all" and fit.fraction == 1.0
    assert fit.delta == pytest.approx(0.04, abs=3 * fit.delta_sigma)
    r, s_r = mean_rel_diff(1.04 * a, 1.04 * sa, b, sb, np.ones(N))
    assert r == pytest.approx(0.04, abs=3 * s_r)


def test_a_ten_percent_bump_is_found_in_its_structure_and_nowhere_else(two_runs):
    (_, _), (b, sb) = two_runs
    bump = (X > 0.30) & (X < 0.35)  # 2.5 % of the points
    c, sc = run(3, np.where(bump, 1.1 * TRUE, TRUE))
    structures = {"holds the bump": X > 0.0, "left": (X < 0.0) & (X > -0.5), "far left": X < -0.5}
    rows = {}
    for name, mask in structures.items():
        rows[name], post = structure_significance(c[mask], sc[mask], b[mask], sb[mask],
                                                  np.ones(mask.sum()), np.ones(mask.sum(), bool))
        if name == "holds the bump":
            inside = bump[mask]
            assert np.nanmean(post[inside]) > 3 * np.nanmean(post[~inside])
    hot = rows["holds the bump"]
    assert hot["systematic_model"] == "part"
    assert hot["systematic_rel_diff"] == pytest.approx(0.10, abs=3 * hot["systematic_rel_diff_sigma"])
    assert hot["systematic_fraction"] == pytest.approx(0.05, abs=3 * hot["systematic_fraction_sigma"])
    for name in ("left", "far left"):
        row = rows[name]
        assert row["systematic_model"] == "none" and row["systematic_fraction"] == 0.0
        assert abs(row["systematic_rel_diff"]) <= 0.01
        assert row["mean_rel_diff_consistent_with_zero"]


def test_raw_batch_sigmas_would_fake_a_systematic_part_and_pooling_prevents_it(two_runs):
    """Why σ is pooled: a mixture fitted with the batches' own (noisy) σ finds a 'part'."""
    (a, sa), (b, sb) = two_runs
    raw, _ = systematic_fit(a, sa, b, sb, pool=False)
    pooled, _ = systematic_fit(a, sa, b, sb)
    assert raw.log_likelihood["part"] - raw.log_likelihood["none"] > 10.0
    assert pooled.log_likelihood["part"] - pooled.log_likelihood["none"] < 5.0


def test_pooled_sigma_recovers_the_true_sigma(two_runs):
    (a, sa), _ = two_runs
    pooled = pooled_sigma(a, sa)
    assert np.median(pooled / (REL * TRUE)) == pytest.approx(1.0, abs=0.03)
    assert np.std(pooled / (REL * TRUE)) < 0.5 * np.std(sa / (REL * TRUE))


def test_mean_rel_diff_and_its_sigma_analytic():
    a, b = np.full(100, 1.1), np.full(100, 1.0)
    sa, sb = np.full(100, 0.2), np.full(100, 0.1)
    r, s_r = mean_rel_diff(a, sa, b, sb, np.ones(100))
    assert r == pytest.approx(0.1)
    assert s_r == pytest.approx(np.sqrt(100 * (0.04 + 1.21 * 0.01)) / 100)
    z = normalised_difference(a, sa, b, sb)
    assert z == pytest.approx(np.full(100, 0.1 / np.sqrt(0.05)))
    assert np.isnan(normalised_difference(a, 0 * sa, b, 0 * sb)).all()


def test_doses_without_sigma_are_compared_as_exact_and_said_so():
    a, b = np.full(50, 1.02), np.ones(50)
    row, post = structure_significance(a, np.zeros(50), b, np.zeros(50), np.ones(50),
                                       np.ones(50, bool))
    assert row["mean_rel_diff"] == pytest.approx(0.02) and row["mean_rel_diff_sigma"] == 0.0
    assert row["systematic_rel_diff"] is None and "compared as exact" in row["systematic_model"]
    assert np.isnan(post).all()
