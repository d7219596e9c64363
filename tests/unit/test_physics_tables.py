"""Kernel tables of CrossSections: totals vs per-process lookup, branching fractions, the cache."""

import math
import warnings

import numpy as np
import pytest
from numba import njit

from tetdose._random import seed_for
from tetdose.transport.physics import _photon as _physics
from tetdose.transport.physics import xs as xs_module
from tetdose.transport.physics._photon import (
    COHERENT,
    ELECTRON_MASS_MEV,
    INCOHERENT,
    PAIR,
    PHOTOELECTRIC,
    interact,
)
from tetdose.transport.physics.xs import MATERIALS, Material, build_cross_sections

#: The media outside the ICRP 110 and ICRU 46 phantom libraries (those are checked, cheaply, in
#: test_composition_library.py): kernel tables for ~200 media would only slow this module down.
NAMES = [n for n in MATERIALS if not n.startswith(("icrp110_", "icru46_"))]
THRESHOLD_MEV = 2.0 * ELECTRON_MASS_MEV
N_SAMPLES = 2_000_000
Z_MAX = 4.0
#: Fractions of a grid interval: on and near the nodes, and between them.
FRACTIONS = (0.0, 1e-9, 1e-6, 0.25, 0.5, 0.75, 1.0 - 1e-6, 1.0 - 1e-9)


@pytest.fixture(scope="module")
def xs():
    return build_cross_sections(NAMES)


@njit
def _kernel_and_lookup(xs, material, energies):
    """Rows: transport_coefficients (μ_t, μen), lookup (μ_incoh + μ_photo + μ_pair, μen)."""
    out = np.empty((energies.size, 4))
    for j in range(energies.size):
        out[j, 0], out[j, 1] = _physics.transport_coefficients(xs, material, energies[j])
        _, inc, pe, pair, mu_en = _physics.lookup(xs, material, energies[j])
        out[j, 2], out[j, 3] = inc + pe + pair, mu_en
    return out


@njit
def _process_counts(xs, material, energy_mev, n, seed):
    counts = np.zeros(4, dtype=np.int64)
    for j in range(n):
        counts[interact(xs, material, energy_mev, 0.0, 0.0, 1.0, seed_for(seed, 4, j))[1]] += 1
    return counts


def _grid_energies(xs, fractions):
    """E at ``fractions`` of every grid interval [MeV], kept inside 10 keV–20 MeV."""
    n = xs.ln_mu_transported.shape[1]
    x = np.arange(n - 1)[:, None] + np.asarray(fractions)[None, :]
    e = np.exp(xs.ln_e_min + xs.d_ln_e * x).ravel()
    return e[(e >= 0.01) & (e <= 20.0)]


def test_node_tables_are_the_per_process_values(xs):
    mu = xs.mu_rho_cm2_g
    total = mu[:, :, 1:].sum(axis=2)
    np.testing.assert_allclose(np.exp(xs.ln_mu_transported), total, rtol=1e-14)
    np.testing.assert_allclose(np.exp(xs.ln_mu_en), xs.mu_en_rho_cm2_g, rtol=1e-14)
    np.testing.assert_allclose(xs.p_incoherent, mu[:, :, 1] / total, rtol=1e-14)
    np.testing.assert_allclose(xs.p_pair, mu[:, :, 3] / total, rtol=1e-14)
    below = np.exp(xs.ln_e_min + xs.d_ln_e * np.arange(total.shape[1])) < THRESHOLD_MEV
    assert np.all(xs.p_pair[:, below] == 0.0) and np.all(xs.p_pair[:, ~below] > 0.0)
    assert np.all(xs.p_incoherent + xs.p_pair < 1.0)  # photoelectric is never 0 here


def test_transport_coefficients_match_lookup_sum(xs):
    """Log–log of the total vs the sum of per-process log–log: measured max 5.2e-5 (air, 28 keV)."""
    energies = _grid_energies(xs, FRACTIONS)
    nodes = _grid_energies(xs, (0.0,))
    worst = 0.0
    for m in range(len(NAMES)):
        got = _kernel_and_lookup(xs, m, energies)
        rel = np.abs(got[:, 0] / got[:, 2] - 1.0)
        worst = max(worst, rel.max())
        np.testing.assert_allclose(got[:, 1], got[:, 3], rtol=1e-12)  # μen: same interpolation
        on_node = _kernel_and_lookup(xs, m, nodes)
        np.testing.assert_allclose(on_node[:, 0], on_node[:, 2], rtol=1e-13)
    assert worst < 1e-4, worst


@pytest.mark.parametrize("energy_mev", [0.03, 0.1, 1.03, 1.1, 10.0])
@pytest.mark.parametrize("name", ["water", "cortical_bone"])
def test_interact_process_frequencies_follow_lookup_ratios(xs, name, energy_mev):
    """Binomial z-test per process; at 1.1 MeV pair is 1.6e-5 (water) – 2.6e-5 (bone) of μ_t."""
    m = NAMES.index(name)
    counts = _process_counts(xs, m, energy_mev, N_SAMPLES, 11)
    _, inc, pe, pair, _ = _physics.lookup(xs, m, energy_mev)
    total = inc + pe + pair
    assert counts[COHERENT] == 0 and counts.sum() == N_SAMPLES
    for code, mu in ((INCOHERENT, inc), (PHOTOELECTRIC, pe), (PAIR, pair)):
        p = mu / total
        if p == 0.0:  # pair below 2mc²
            assert counts[code] == 0
            continue
        z = (counts[code] - N_SAMPLES * p) / math.sqrt(N_SAMPLES * p * (1.0 - p))
        assert abs(z) < Z_MAX, (code, counts[code], N_SAMPLES * p)


@pytest.mark.parametrize("energy_mev", [THRESHOLD_MEV * (1.0 - 1e-9), THRESHOLD_MEV])
@pytest.mark.parametrize("name", ["water", "cortical_bone"])
def test_no_pair_production_at_or_below_threshold(xs, name, energy_mev):
    m = NAMES.index(name)
    x = (math.log(energy_mev) - xs.ln_e_min) / xs.d_ln_e
    i = math.floor(x)
    assert xs.p_pair[m, i] + (x - i) * (xs.p_pair[m, i + 1] - xs.p_pair[m, i]) > 0.0  # guarded
    counts = _process_counts(xs, m, energy_mev, N_SAMPLES, 12)
    assert counts[PAIR] == 0 and counts[INCOHERENT] > 0 and counts[PHOTOELECTRIC] > 0


def test_threshold_guard_with_large_pair_fraction(xs):
    """Tables with p_incoh = 0.25, p_pair = 0.5 everywhere: no pair at E ≤ 2mc², half above."""
    def fixed(p):
        table = np.full_like(xs.p_pair, p)
        table.flags.writeable = False
        return table

    toy = xs._replace(p_incoherent=fixed(0.25), p_pair=fixed(0.5))
    n = 100_000
    for energy_mev in (0.5, THRESHOLD_MEV):
        counts = _process_counts(toy, 0, energy_mev, n, 13)
        assert counts[PAIR] == 0
        assert abs(counts[INCOHERENT] - 0.25 * n) < Z_MAX * math.sqrt(n * 0.25 * 0.75)
    counts = _process_counts(toy, 0, THRESHOLD_MEV * (1.0 + 1e-12), n, 13)
    assert abs(counts[PAIR] - 0.5 * n) < Z_MAX * math.sqrt(n * 0.25)


def test_tables_are_cached_by_names_and_grid():
    a = build_cross_sections(["water", "cortical_bone"])
    assert build_cross_sections(("water", "cortical_bone")) is a
    assert build_cross_sections(["water", "cortical_bone"], 0.01, 20.0, 200) is a
    assert build_cross_sections(["cortical_bone", "water"]) is not a
    assert build_cross_sections(["water", "cortical_bone"], points_per_decade=100) is not a
    fresh = build_cross_sections([MATERIALS["water"], "cortical_bone"])  # by composition
    assert fresh is not a
    assert build_cross_sections([MATERIALS["water"], "cortical_bone"]) is fresh
    same = Material("my_water", MATERIALS["water"].mass_fractions, 1.0, "test")
    assert build_cross_sections([same, "cortical_bone"]) is not fresh  # another name
    for got, want in zip(fresh, a, strict=True):
        np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("material", ["water", MATERIALS["water"]])
def test_tables_are_read_only(material):
    tables = build_cross_sections([material])
    for table in tables[2:]:
        assert not table.flags.writeable
        with pytest.raises(ValueError, match="read-only"):
            table[(0,) * table.ndim] = 1.0
    assert _physics.transport_coefficients(tables, 0, 1.0)[0] > 0.0  # kernels take read-only


def test_cached_call_does_not_warn_again():
    xs_module._cached_tables.cache_clear()
    for expected in (True, False):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            build_cross_sections(["cortical_bone"], e_min_mev=0.001, points_per_decade=5)
        edge = [w for w in caught if "absorption edge" in str(w.message)]
        assert bool(edge) is expected
        assert all(w.filename == __file__ for w in edge)
