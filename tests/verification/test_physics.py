"""Interaction kernels vs analytic Klein–Nishina, cross-section ratios and conservation laws."""

import math

import numpy as np
import pytest
from numba import njit
from scipy import stats

from tetdose._random import seed_for
from tetdose.transport.physics import _photon as _physics
from tetdose.transport.physics._photon import (
    ELECTRON_MASS_MEV,
    INCOHERENT,
    PAIR,
    PHOTOELECTRIC,
    interact,
    isotropic_direction,
    klein_nishina_inverse,
    rotate_direction,
    sample_klein_nishina,
)
from tetdose.transport.physics.xs import build_cross_sections, mass_coefficients, transfer_coefficients

N_SAMPLES = 100_000
SIGMAS = 4.0


@pytest.fixture(scope="module")
def xs():
    return build_cross_sections(["water", "cortical_bone"])


@njit
def _kn_samples(energy_mev, n, seed):
    out = np.empty((n, 2))
    for i in range(n):
        _, out[i, 0], out[i, 1] = sample_klein_nishina(energy_mev, seed_for(seed, 0, i))
    return out


@njit
def _kn_inverse(energy_mev, xi):
    out = np.empty((len(xi), 2))
    for i in range(len(xi)):
        out[i, 0], out[i, 1] = klein_nishina_inverse(energy_mev, xi[i])
    return out


@njit
def _interactions(xs, material, energy_mev, u, v, w, n, seed):
    """Rows: process, deposited, e_out, u2, v2, w2, e_secondary, su, sv, sw."""
    out = np.empty((n, 10))
    for i in range(n):
        _, proc, dep, e_out, u2, v2, w2, e_sec, su, sv, sw = interact(
            xs, material, energy_mev, u, v, w, seed_for(seed, 1, i))
        out[i, 0], out[i, 1], out[i, 2] = proc, dep, e_out
        out[i, 3], out[i, 4], out[i, 5] = u2, v2, w2
        out[i, 6], out[i, 7], out[i, 8], out[i, 9] = e_sec, su, sv, sw
    return out


@njit
def _isotropic(n, seed):
    out = np.empty((n, 3))
    for i in range(n):
        _, out[i, 0], out[i, 1], out[i, 2] = isotropic_direction(seed_for(seed, 2, i))
    return out


def _kn_antiderivative(eps, k):
    """∫ (ε + 1/ε − sin²θ) dε with cos θ = c − 1/(kε), c = 1 + 1/k (exact)."""
    c = 1.0 + 1.0 / k
    return eps**2 / 2 + np.log(eps) * (1.0 - 2.0 * c / k) + (c * c - 1.0) * eps - 1.0 / (k * k * eps)


def _kn_mean(fn, k):
    """Mean of fn(ε) under dσ/dε ∝ ε + 1/ε − sin²θ (Gauss–Legendre, 400 nodes)."""
    x, w = np.polynomial.legendre.leggauss(400)
    eps0 = 1.0 / (1.0 + 2.0 * k)
    eps = eps0 + (1.0 - eps0) * (x + 1.0) / 2.0
    t = (1.0 / eps - 1.0) / k
    density = eps + 1.0 / eps - t * (2.0 - t)
    return (density * fn(eps)) @ w / (density @ w)


@pytest.mark.parametrize("energy_mev", [0.1, 1.0, 10.0])
def test_klein_nishina_sampler_matches_analytic_distribution(energy_mev):
    k = energy_mev / ELECTRON_MASS_MEV
    samples = _kn_samples(energy_mev, N_SAMPLES, 7)
    eps, cos_theta = samples[:, 0] / energy_mev, samples[:, 1]
    eps0 = 1.0 / (1.0 + 2.0 * k)
    assert np.all((eps >= eps0 * (1 - 1e-12)) & (eps <= 1.0))
    # Compton kinematics tie the two outputs together
    np.testing.assert_allclose(eps, 1.0 / (1.0 + k * (1.0 - cos_theta)), rtol=1e-12)
    # binned χ² in ε against the exact integral of dσ/dε
    edges = np.linspace(eps0, 1.0, 51)
    cdf = _kn_antiderivative(edges, k)
    expected = N_SAMPLES * np.diff(cdf) / (cdf[-1] - cdf[0])
    observed, _ = np.histogram(eps, bins=edges)
    chi2 = float(((observed - expected) ** 2 / expected).sum())
    assert stats.chi2.sf(chi2, df=len(expected) - 1) > 1e-4, chi2
    # moments: energy transfer fraction and cos θ
    for values, fn in (
        (1.0 - eps, lambda e: 1.0 - e),
        (cos_theta, lambda e: 1.0 - (1.0 / e - 1.0) / k),
    ):
        sigma = values.std() / math.sqrt(N_SAMPLES)
        assert abs(values.mean() - _kn_mean(fn, k)) < SIGMAS * sigma


@pytest.mark.parametrize("energy_mev", [0.015, 0.1, 1.0, 6.0, 20.0])
def test_klein_nishina_inverse_inverts_the_analytic_cdf(energy_mev):
    """The quasi-random Compton sampler (inversion): the exact CDF (the antiderivative above, an
    independent form of the one the kernel solves) at its ε is ξ to 1e-9, ε rises with ξ from
    ε₀ to 1, Compton kinematics hold, and a uniform grid of ξ has the rejection sampler's
    distribution (two-sample KS)."""
    k = energy_mev / ELECTRON_MASS_MEV
    eps0 = 1.0 / (1.0 + 2.0 * k)
    xi = np.concatenate([[0.0], (np.arange(20_000) + 0.5) / 20_000, [1.0 - 1e-12]])
    out = _kn_inverse(energy_mev, xi)
    eps, cos_theta = out[:, 0] / energy_mev, out[:, 1]
    lo, hi = _kn_antiderivative(np.array([eps0, 1.0]), k)
    np.testing.assert_allclose((_kn_antiderivative(eps, k) - lo) / (hi - lo), xi, rtol=0,
                               atol=1e-9)
    assert eps[0] == pytest.approx(eps0, rel=1e-12) and eps[-1] == pytest.approx(1.0, abs=1e-6)
    assert np.all(np.diff(eps) > 0)
    np.testing.assert_allclose(eps, 1.0 / (1.0 + k * (1.0 - cos_theta)), rtol=1e-12)
    ref = _kn_samples(energy_mev, N_SAMPLES, 11)[:, 0] / energy_mev
    assert stats.ks_2samp(eps[1:-1], ref).pvalue > 1e-3


@pytest.mark.parametrize(
    ("material", "energy_mev"), [(0, 0.03), (1, 0.05), (0, 1.0), (0, 5.0), (1, 15.0)]
)
def test_interact_conserves_energy_and_samples_processes_by_cross_section(
    xs, material, energy_mev
):
    d = np.array([1.0, -2.0, 3.0]) / math.sqrt(14.0)
    r = _interactions(xs, material, energy_mev, d[0], d[1], d[2], N_SAMPLES, 3)
    process, deposited, e_out, e_sec = r[:, 0], r[:, 1], r[:, 2], r[:, 6]
    np.testing.assert_allclose(deposited + e_out + e_sec, energy_mev, rtol=1e-12)
    assert np.all(deposited >= 0.0) and np.all(e_out >= 0.0)
    _, inc, pe, pair, _ = _physics.lookup(xs, material, energy_mev)
    total = inc + pe + pair
    for code, mu in ((INCOHERENT, inc), (PHOTOELECTRIC, pe), (PAIR, pair)):
        p = mu / total
        sigma = math.sqrt(N_SAMPLES * p * (1.0 - p))
        assert abs(np.count_nonzero(process == code) - N_SAMPLES * p) <= SIGMAS * sigma + 1e-9
    assert set(np.unique(process)) <= {INCOHERENT, PHOTOELECTRIC, PAIR}
    moving = e_out > 0.0
    np.testing.assert_allclose(np.linalg.norm(r[moving, 3:6], axis=1), 1.0, rtol=1e-12)
    # photoelectric: everything local, direction untouched
    photo = process == PHOTOELECTRIC
    np.testing.assert_array_equal(deposited[photo], energy_mev)
    np.testing.assert_array_equal(r[photo, 3:6], np.broadcast_to(d, (photo.sum(), 3)))
    # incoherent: the deflection angle obeys Compton kinematics
    comp = process == INCOHERENT
    cos_theta = r[comp, 3:6] @ d
    k = energy_mev / ELECTRON_MASS_MEV
    np.testing.assert_allclose(
        e_out[comp], energy_mev / (1.0 + k * (1.0 - cos_theta)), rtol=1e-9
    )
    assert np.all(e_sec[~(process == PAIR)] == 0.0)


@pytest.mark.parametrize(
    ("material", "energy_mev"), [(0, 0.08), (1, 0.03), (0, 1.25), (1, 8.0)]
)
def test_mean_local_deposit_equals_transfer_coefficient(xs, material, energy_mev):
    """E·μtr/μ (independent quadrature of Klein–Nishina) = mean deposit of ``interact``."""
    r = _interactions(xs, material, energy_mev, 0.0, 1.0, 0.0, N_SAMPLES, 8)
    name = ("water", "cortical_bone")[material]
    mu = mass_coefficients(name, [energy_mev])[0][0, 1:].sum()  # coherent is not transported
    expected = energy_mev * transfer_coefficients(name, [energy_mev])[0] / mu
    sigma = r[:, 1].std() / math.sqrt(N_SAMPLES)
    assert abs(r[:, 1].mean() - expected) < SIGMAS * sigma + 2e-4 * expected  # + table interp.


def test_pair_threshold_and_annihilation_photons(xs):
    below = _interactions(xs, 1, 2.0 * ELECTRON_MASS_MEV * (1.0 - 1e-9), 0.0, 0.0, 1.0,
                          N_SAMPLES, 5)
    assert not np.any(below[:, 0] == PAIR)
    r = _interactions(xs, 1, 20.0, 0.0, 0.0, 1.0, N_SAMPLES, 6)
    pair = r[r[:, 0] == PAIR]
    assert len(pair) > 1000
    np.testing.assert_array_equal(pair[:, 2], ELECTRON_MASS_MEV)
    np.testing.assert_array_equal(pair[:, 6], ELECTRON_MASS_MEV)
    np.testing.assert_allclose(pair[:, 1], 20.0 - 2.0 * ELECTRON_MASS_MEV, rtol=1e-12)
    np.testing.assert_allclose(pair[:, 3:6], -pair[:, 7:10], rtol=0, atol=0)
    # isotropic: each direction component has mean 0 and variance 1/3
    n = len(pair)
    for c in range(3, 6):
        assert abs(pair[:, c].mean()) < SIGMAS * math.sqrt(1.0 / 3.0 / n)
        assert abs((pair[:, c] ** 2).mean() - 1.0 / 3.0) < SIGMAS * math.sqrt(4.0 / 45.0 / n)


@pytest.mark.parametrize(
    "direction", [(0.0, 0.0, 1.0), (0.0, 0.0, -1.0), (0.6, 0.0, 0.8), (1.0, 2.0, -2.0)]
)
def test_rotate_direction_gives_the_requested_angle(direction):
    d = np.array(direction) / np.linalg.norm(direction)
    n_phi = 64
    for cos_theta in (-1.0, -0.3, 0.0, 0.5, 0.999999, 1.0):
        out = np.array([
            rotate_direction(d[0], d[1], d[2], cos_theta, 2.0 * math.pi * j / n_phi)
            for j in range(n_phi)
        ])
        np.testing.assert_allclose(np.linalg.norm(out, axis=1), 1.0, rtol=1e-14)
        np.testing.assert_allclose(out @ d, cos_theta, atol=1e-12)
        # φ uniform: the cone averages to cos θ · d (sin θ components cancel)
        np.testing.assert_allclose(out.mean(axis=0), cos_theta * d, atol=1e-12)


def test_isotropic_direction_moments():
    n = 50_000
    dirs = _isotropic(n, 9)
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=1), 1.0, rtol=1e-14)
    assert np.all(np.abs(dirs.mean(axis=0)) < SIGMAS * math.sqrt(1.0 / 3.0 / n))
