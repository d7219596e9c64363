"""Electron/positron samplers against their analytic distributions and conservation laws."""

import math

import numpy as np
import pytest
from numba import njit
from scipy.integrate import quad

from tetdose._random import seed_for
from tetdose.transport.physics import _electron as ke
from tetdose.transport.physics import electron_xs as ex

MC2 = ex.ELECTRON_MASS_MEV
N = 200_000


@njit(cache=True)
def _draw_binary(kind, e, cutoff, n, seed):
    out = np.empty((n, 3))
    state = seed_for(seed, 0, 0)
    for j in range(n):
        if kind == 0:
            state, t, c1, c2 = ke.sample_moller(e, cutoff, state)
        else:
            state, t, c1, c2 = ke.sample_bhabha(e, cutoff, state)
        out[j, 0], out[j, 1], out[j, 2] = t, c1, c2
    return out


@njit(cache=True)
def _draw_brems(et, m, e, n, seed):
    out = np.empty((n, 2))
    state = seed_for(seed, 1, 0)
    for j in range(n):
        state, k, c = ke.sample_brems(et, m, 0, e, state)
        out[j, 0], out[j, 1] = k, c
    return out


@njit(cache=True)
def _draw_annihilation(e, n, seed):
    out = np.empty((n, 4))
    state = seed_for(seed, 2, 0)
    for j in range(n):
        state, k1, c1, k2, c2 = ke.sample_annihilation_in_flight(e, state)
        out[j, 0], out[j, 1], out[j, 2], out[j, 3] = k1, c1, k2, c2
    return out


@njit(cache=True)
def _draw_ms(et, e, s, n, seed):
    out = np.empty(n)
    state = seed_for(seed, 3, 0)
    for j in range(n):
        state, out[j] = ke.sample_ms_cos(et, 0, 0, e, s, state)
    return out


def _chi2_against(samples, edges, cdf):
    """χ² per degree of freedom of a histogram against the expected counts from a CDF."""
    counts, _ = np.histogram(samples, edges)
    expected = len(samples) * np.diff([cdf(x) for x in edges])
    return float(np.sum((counts - expected) ** 2 / expected) / (len(counts) - 1))


@pytest.mark.parametrize(("kind", "e", "top"), [(0, 1.0, 0.5), (0, 0.3, 0.5), (1, 1.0, 1.0), (1, 0.15, 1.0)])
def test_moller_and_bhabha_energies_follow_their_dcs(kind, e, top):
    cut = 0.01
    tau = e / MC2
    if kind == 0:
        def rej(x):
            return ke.moller_rejection(x, tau)
    else:
        def rej(x):
            return ke.bhabha_rejection(x, tau)
    grid = np.linspace(cut / e, top, 2001)
    bound = 1.0 + 1.25 * (tau / (tau + 1.0)) ** 2 if kind == 0 else 1.0
    values = np.array([rej(x) for x in grid])
    assert np.all(values <= bound * (1 + 1e-12)) and np.all(values >= 0.0)  # rejection is valid
    draws = _draw_binary(kind, e, cut, N, 11)
    eps = draws[:, 0] / e
    assert eps.min() >= cut / e and eps.max() <= top
    norm = quad(lambda x: rej(x) / x**2, cut / e, top, limit=200)[0]
    edges = np.geomspace(cut / e, top, 21)
    chi2 = _chi2_against(eps, edges, lambda x: quad(lambda y: rej(y) / y**2, cut / e, x, limit=200)[0] / norm)
    assert chi2 < 2.0
    # kinematics: exact energy split, angles from two-body kinematics
    t_prim = e - draws[:, 0]
    assert np.all(np.abs(t_prim + draws[:, 0] - e) <= 1e-12 * e)
    cos_p = np.sqrt(t_prim * (e + 2 * MC2) / (e * (t_prim + 2 * MC2)))
    np.testing.assert_allclose(draws[:, 1], cos_p, rtol=1e-12)


def test_moller_below_twice_the_cutoff_returns_no_delta():
    assert ke.sample_moller(0.015, 0.01, np.uint64(5))[1] == 0.0
    assert ke.sample_bhabha(0.009, 0.01, np.uint64(5))[1] == 0.0


@pytest.fixture(scope="module")
def tables():
    return ex.build_electron_tables(["water", "cortical_bone"], cutoff_mev=0.05, photon_cutoff_mev=0.01)


@pytest.mark.parametrize("e", [0.5, 5.0, 18.0])
def test_brems_photon_spectrum_and_angle(tables, e):
    kc = tables.photon_cutoff_mev
    z13, c = tables.brems_z13[1], tables.brems_c[1]
    draws = _draw_brems(tables, 1, e, N, 7)
    k = draws[:, 0]
    assert k.min() >= kc * (1 - 1e-12) and k.max() <= e
    assert np.all(ke.brems_chi(z13, c, e, 1e-9) <= 2 * (20.867 - c))

    def density(x):
        return ke.brems_chi(z13, c, e, x) / x

    norm = quad(density, kc / e, 1.0, limit=400)[0]
    edges = np.geomspace(kc / e, 1.0, 21)
    chi2 = _chi2_against(k / e, edges, lambda x: quad(density, kc / e, x, limit=400)[0] / norm)
    assert chi2 < 2.0
    # photon polar angle: p(μ) ∝ (1 − βμ)⁻², its mean (1/β²)[... ] computed by quadrature
    beta = math.sqrt(1.0 - 1.0 / (e / MC2 + 1.0) ** 2)
    w = quad(lambda mu: 1.0 / (1.0 - beta * mu) ** 2, -1, 1, points=[1.0])[0]
    mean = quad(lambda mu: mu / (1.0 - beta * mu) ** 2, -1, 1, points=[1.0])[0] / w
    sd = np.std(draws[:, 1]) / math.sqrt(N)
    assert abs(draws[:, 1].mean() - mean) < 5 * sd


@pytest.mark.parametrize("e", [0.01, 0.5, 3.0, 15.0])
def test_annihilation_in_flight_conserves_energy_and_momentum(e):
    draws = _draw_annihilation(e, N, 3)
    k1, c1, k2, c2 = draws.T
    etot = e + 2 * MC2
    assert np.all(np.abs(k1 + k2 - etot) <= 1e-12 * etot)
    p = math.sqrt(e * (e + 2 * MC2))  # positron momentum [MeV/c]
    np.testing.assert_allclose(k1 * c1 + k2 * c2, p, rtol=1e-9, atol=1e-9)  # along the positron
    np.testing.assert_allclose(k1 * np.sqrt(1 - c1**2), k2 * np.sqrt(1 - c2**2), rtol=1e-6, atol=1e-7)
    g = e / MC2 + 1.0
    pp = math.sqrt(g * g - 1.0)
    zmin = 1.0 / (g + 1.0 + pp)

    def s(z):  # Heitler: dσ/dζ ∝ S(ζ) + S(1 − ζ); the sampler draws k1 from S alone on [ζmin, 1 − ζmin]
        return -((g + 1.0) ** 2) + (g * g + 4.0 * g + 1.0) / z - 1.0 / z**2

    norm = quad(s, zmin, 1 - zmin, limit=200)[0]
    edges = np.linspace(zmin, 1 - zmin, 21)
    assert _chi2_against(k1 / etot, edges, lambda x: quad(s, zmin, x, limit=200)[0] / norm) < 2.0


def test_wentzel_screening_solves_the_first_moment():
    for m1 in np.geomspace(1e-9, 1 - 1e-6, 60):
        a = ke.wentzel_screening(m1)
        assert ke.wentzel_mean(a) == pytest.approx(m1, rel=1e-9)


@pytest.mark.parametrize("s_over_l1", [1e-3, 0.05, 0.5, 3.0])
def test_multiple_scattering_has_the_exact_first_and_second_moments(tables, s_over_l1):
    """⟨1 − μ⟩ = 1 − exp(−s/λ₁) and ⟨P₂(μ)⟩ = exp(−s/λ₂) (Goudsmit–Saunderson), the second
    moment through the mixture of the Wentzel shape and a fixed deflection."""
    e = 2.0
    s = s_over_l1 / ke.lambda1_inverse(tables, 0, 0, e)
    mu = _draw_ms(tables, e, s, N, 5)
    target = -math.expm1(-s_over_l1)
    sd = np.std(1.0 - mu) / math.sqrt(N)
    assert abs(np.mean(1.0 - mu) - target) < max(4 * sd, 1e-3 * target)
    if s_over_l1 >= 0.05:  # below, the Rutherford tail makes the sample mean too noisy for 1 %
        assert np.mean(1.0 - mu) == pytest.approx(target, rel=0.01)
    p2 = 1.5 * mu**2 - 0.5
    target2 = math.exp(-s * ke.lambda2_inverse(tables, 0, 0, e))
    assert abs(p2.mean() - target2) < 4 * p2.std() / math.sqrt(N)
    assert mu.min() >= -1.0 and mu.max() <= 1.0


def test_wentzel_alone_would_overstate_the_second_moment(tables):
    """The Wentzel shape fitted to the first moment has ⟨(1 − μ)²⟩ 70 % above the GS value at
    s/λ₁ = 0.1 for 2 MeV in water (the reason for the mixture), and the inversion
    μ(u) = 1 − 2Au/(1 + A − u) has both moments of the closed forms (quadrature over u)."""
    e = 2.0
    s = 0.1 / ke.lambda1_inverse(tables, 0, 0, e)
    g1 = -math.expm1(-0.1)
    a = ke.wentzel_screening(g1)
    t2 = (3 * g1 + math.expm1(-s * ke.lambda2_inverse(tables, 0, 0, e))) / 1.5
    assert 1.5 < ke.wentzel_second(a) / t2 < 1.9
    assert quad(lambda u: 2 * a * u / (1 + a - u), 0, 1, limit=200)[0] == pytest.approx(g1, rel=1e-8)
    assert quad(lambda u: (2 * a * u / (1 + a - u)) ** 2, 0, 1, limit=200)[0] == pytest.approx(
        ke.wentzel_second(a), rel=1e-8)


def test_multiple_scattering_limits(tables):
    assert ke.sample_ms_cos(tables, 0, 0, 1.0, 0.0, np.uint64(1))[1] == 1.0
    mu = _draw_ms(tables, 1.0, 1e3, N, 9)  # s ≫ λ₁: isotropic
    assert abs(mu.mean()) < 5 / math.sqrt(3 * N) and abs(np.mean(mu**2) - 1 / 3) < 5e-3
