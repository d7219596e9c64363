"""Interaction data: materials, μ/ρ and μen/ρ tables vs NIST, the lookup kernel."""

import math
import warnings
from pathlib import Path

import numpy as np
import pytest

from tetdose.errors import PlanError
from tetdose.transport.physics import _photon as _physics
from tetdose.transport.physics.xs import (
    CLASSICAL_ELECTRON_RADIUS_CM,
    DENSITY_CLASS_MATERIALS,
    DENSITY_CLASS_UPPER_G_CM3,
    ELECTRON_MASS_MEV,
    MATERIALS,
    Material,
    build_cross_sections,
    kn_cross_section_cm2,
    mass_coefficients,
    material_for_density,
)

NIST_DIR = Path(__file__).resolve().parents[2] / ".." / "shared" / "reference" / "nist"
#: our material name → NIST SRD 126 file (as shipped in roentgen)
NIST_FILES = {
    "water": "water", "air": "air", "lung": "lung", "adipose": "adipose",
    "soft_tissue": "tissue", "soft_tissue_4": "tissue4", "muscle": "muscle",
    "blood": "blood", "cortical_bone": "bone",
}
NAMES = list(NIST_FILES)


@pytest.fixture(scope="module")
def xs():
    return build_cross_sections(NAMES)


def _nist(name):
    path = NIST_DIR / f"{NIST_FILES[name]}.csv"
    if not path.exists():
        pytest.skip(f"NIST reference tables not found at {path} (../shared beside the checkout)")
    table = np.loadtxt(path, delimiter=",", comments="#")
    keep = (table[:, 0] >= 0.01 - 1e-12) & (table[:, 0] <= 20.0 + 1e-12)
    return table[keep]


def _lookup_all(xs, m, energies):
    return np.array([_physics.lookup(xs, m, float(e)) for e in energies])


@pytest.mark.parametrize("name", NAMES)
def test_tables_match_nist_within_one_percent(xs, name):
    ref = _nist(name)
    got = _lookup_all(xs, NAMES.index(name), ref[:, 0])
    mu_total = got[:, :4].sum(axis=1)  # NIST μ/ρ includes coherent scattering
    np.testing.assert_allclose(mu_total, ref[:, 1], rtol=0.01)
    np.testing.assert_allclose(got[:, 4], ref[:, 2], rtol=0.01)


def test_water_at_1_mev_matches_nist_values():
    mu, mu_en = mass_coefficients("water", [1.0])
    assert mu.sum() == pytest.approx(0.07072, rel=0.01)
    assert mu_en[0] == pytest.approx(0.03103, rel=0.01)


def test_lookup_equals_direct_evaluation_on_grid_nodes(xs):
    k = np.array([0, 1, 57, 300, 661])
    energies = np.exp(xs.ln_e_min + xs.d_ln_e * k)
    for m in (0, NAMES.index("cortical_bone")):
        got = _lookup_all(xs, m, energies)
        mu, mu_en = mass_coefficients(NAMES[m], energies)
        np.testing.assert_allclose(got[:, :4], mu, rtol=1e-12, atol=1e-300)
        np.testing.assert_allclose(got[:, 4], mu_en, rtol=1e-12)


def test_lookup_off_grid_within_interpolation_error(xs):
    rng = np.random.default_rng(4)
    energies = np.exp(rng.uniform(math.log(0.0101), math.log(19.9), 400))
    for m in (0, NAMES.index("cortical_bone")):
        got = _lookup_all(xs, m, energies)
        mu, mu_en = mass_coefficients(NAMES[m], energies)
        # pair rises from 0 at threshold, so its relative error there is measured against μ_total
        tolerance = 2e-3 * mu + 1e-4 * mu.sum(axis=1, keepdims=True)
        assert np.all(np.abs(got[:, :4] - mu) <= tolerance)
        np.testing.assert_allclose(got[:, 4], mu_en, rtol=2e-3)


def test_lookup_pair_threshold_and_clamping(xs):
    threshold = 2.0 * ELECTRON_MASS_MEV
    assert _physics.lookup(xs, 0, threshold * (1 - 1e-9))[3] == 0.0
    assert _physics.lookup(xs, 0, 1.0)[3] == 0.0
    assert _physics.lookup(xs, 0, 1.5)[3] > 0.0
    # outside the grid: the end values, never extrapolated
    assert _physics.lookup(xs, 0, 0.001) == _physics.lookup(xs, 0, 0.01)
    top = math.exp(xs.ln_e_min + xs.d_ln_e * (xs.mu_rho_cm2_g.shape[1] - 1))
    assert _physics.lookup(xs, 0, 50.0) == pytest.approx(_physics.lookup(xs, 0, top), rel=1e-12)


def test_transport_coefficients_leave_out_coherent(xs):
    coh, inc, pe, pair, mu_en = _physics.lookup(xs, 0, 0.03)
    assert coh > 0.0
    mu_t, mu_en_t = _physics.transport_coefficients(xs, 0, 0.03)
    assert mu_t == pytest.approx(inc + pe + pair, rel=1e-4)  # coherent is 13 % of μ here
    assert mu_en_t == pytest.approx(mu_en, rel=1e-12)


def test_table_layout(xs):
    assert xs.mu_rho_cm2_g.shape == (len(NAMES), 662, 4)
    for table in xs[2:]:
        assert table.shape[:2] == (len(NAMES), 662)
        assert table.dtype == np.float64 and table.flags.c_contiguous
        assert not table.flags.writeable
    e_last = math.exp(xs.ln_e_min + xs.d_ln_e * 661)
    assert math.exp(xs.ln_e_min) == pytest.approx(0.01) and e_last == pytest.approx(20.0)


def test_mixture_rule_is_linear_in_mass_fractions():
    half = Material("half", ((1, 0.5), (8, 0.5)), 1.0, "test")
    hydrogen = Material("h", ((1, 1.0),), 1.0, "test")
    oxygen = Material("o", ((8, 1.0),), 1.0, "test")
    e = np.array([0.02, 0.3, 5.0])
    mix = mass_coefficients(half, e)[0]
    np.testing.assert_allclose(
        mix, 0.5 * (mass_coefficients(hydrogen, e)[0] + mass_coefficients(oxygen, e)[0]),
        rtol=1e-12,
    )


def test_klein_nishina_cross_section_against_numerical_integral():
    # Thomson limit, then the integral of dσ/dΩ = r_e²/2 ε²(ε + 1/ε − sin²θ)
    thomson = 8.0 * math.pi / 3.0 * CLASSICAL_ELECTRON_RADIUS_CM**2
    assert kn_cross_section_cm2(1e-5) == pytest.approx(thomson, rel=1e-4)
    x, w = np.polynomial.legendre.leggauss(400)
    for e in (0.1, 1.0, 10.0):
        eps = 1.0 / (1.0 + e / ELECTRON_MASS_MEV * (1.0 - x))
        dsig = 0.5 * CLASSICAL_ELECTRON_RADIUS_CM**2 * eps**2 * (eps + 1 / eps - (1 - x**2))
        assert kn_cross_section_cm2(e) == pytest.approx(2 * math.pi * dsig @ w, rel=1e-6)


def test_density_classes():
    upper = np.array(DENSITY_CLASS_UPPER_G_CM3)
    rho = np.concatenate([[0.0, 0.0012, 0.26, 0.95, 1.0, 1.06, 1.92, 5.0], upper])
    got = material_for_density(rho)
    names = [DENSITY_CLASS_MATERIALS[i] for i in got[:8]]
    assert names == ["air", "air", "lung", "adipose", "soft_tissue", "soft_tissue",
                     "cortical_bone", "cortical_bone"]
    np.testing.assert_array_equal(got[8:], np.arange(1, len(upper) + 1))  # bound: upper class
    assert got.dtype == np.intp
    assert all(name in MATERIALS for name in DENSITY_CLASS_MATERIALS)
    assert material_for_density(np.ones((2, 3))).shape == (2, 3)
    with pytest.raises(PlanError, match="NaN or negative"):
        material_for_density(np.array([1.0, np.nan]))


def test_density_class_bounds_match_documented_schneider_hu():
    from tetdose.core.calibration import HUCalibration

    hu = HUCalibration.schneider2000().hu_of(np.array(DENSITY_CLASS_UPPER_G_CM3))
    np.testing.assert_allclose(hu, [-953, -176, -36, 83], atol=1.0)


def test_invalid_inputs_raise_plan_error():
    with pytest.raises(PlanError, match="unknown material 'bone'"):
        build_cross_sections(["bone"])
    with pytest.raises(PlanError, match="energy range"):
        build_cross_sections(["water"], e_min_mev=0.5, e_max_mev=0.1)
    with pytest.raises(PlanError, match="sum to"):
        Material("bad", ((1, 0.5), (8, 0.4)), 1.0, "test")
    with pytest.raises(PlanError, match="energies must lie"):
        mass_coefficients("water", [100.0])


def test_edge_inside_grid_warns():
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        build_cross_sections([MATERIALS["cortical_bone"]], e_min_mev=0.001, points_per_decade=5)
    edge = [w for w in caught if "absorption edge at 4.0" in str(w.message)]
    assert edge and all(w.filename == __file__ for w in edge)  # points at the caller
