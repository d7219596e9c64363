"""Electron/positron tables against NIST ESTAR, ICRU 37, ELSEPA and their own defining integrals."""

import math

import numpy as np
import pytest
from scipy.integrate import quad

from tetdose.errors import OptionError, PlanError
from tetdose.transport.physics import _electron as ke
from tetdose.transport.physics import electron_xs as ex
from tetdose.transport.physics.materials import Material

# ESTAR compositions (NIST SRD 124 material list, ICRU Report 37): ICRP tissues.
BONE_ICRP = Material("bone_cortical_icrp", ((1, 0.047234), (6, 0.14433), (7, 0.04199), (8, 0.446096),
                                            (12, 0.0022), (15, 0.10497), (16, 0.00315), (20, 0.20993),
                                            (30, 0.0001)), 1.85, "ESTAR")
SOFT_ICRP = Material("tissue_soft_icrp", ((1, 0.104472), (6, 0.23219), (7, 0.02488), (8, 0.630238),
                                          (11, 0.00113), (12, 0.00013), (15, 0.00133), (16, 0.00199),
                                          (17, 0.00134), (19, 0.00199), (20, 0.00023), (26, 5e-05),
                                          (30, 3e-05)), 1.0, "ESTAR")
LUNG_ICRP = Material("lung_icrp", ((1, 0.101278), (6, 0.10231), (7, 0.02865), (8, 0.757072),
                                   (11, 0.00184), (12, 0.00073), (15, 0.0008), (16, 0.00225),
                                   (17, 0.00266), (19, 0.00194), (20, 9e-05), (26, 0.00037),
                                   (30, 1e-05)), 1.05, "ESTAR")
ADIPOSE_ICRP = Material("adipose_icrp", ((1, 0.119477), (6, 0.63724), (7, 0.00797), (8, 0.232333),
                                         (11, 0.0005), (12, 2e-05), (15, 0.00016), (16, 0.00073),
                                         (17, 0.00119), (19, 0.00032), (20, 2e-05), (26, 2e-05),
                                         (30, 2e-05)), 0.92, "ESTAR")
MUSCLE_ICRP = Material("muscle_icrp", ((1, 0.100637), (6, 0.10783), (7, 0.02768), (8, 0.754773),
                                       (11, 0.00075), (12, 0.00019), (15, 0.0018), (16, 0.00241),
                                       (17, 0.00079), (19, 0.00302), (20, 3e-05), (26, 4e-05),
                                       (30, 5e-05)), 1.04, "ESTAR")

ENERGIES = (0.01, 0.1, 1.0, 10.0)
# NIST ESTAR (physics.nist.gov/PhysRefData/Star/Text/ESTAR.html, SRD 124): collision and radiative
# stopping power [MeV cm²/g] and CSDA range [g/cm²] at 0.01, 0.1, 1, 10 MeV, typed from its tables.
ESTAR = {
    "water": ((22.56, 3.898e-3, 2.515e-4), (4.115, 4.228e-3, 1.431e-2), (1.849, 1.280e-2, 0.4367),
              (1.968, 1.814e-1, 4.975)),
    "air": ((19.75, 3.897e-3, 2.884e-4), (3.633, 4.222e-3, 1.623e-2), (1.661, 1.271e-2, 0.4912),
            (1.979, 1.795e-1, 5.192)),
    "bone": ((19.72, 5.461e-3, 2.909e-4), (3.679, 6.356e-3, 1.607e-2), (1.659, 1.824e-2, 0.4857),
             (1.799, 2.476e-1, 5.374)),
    "soft": ((22.57, 3.680e-3, 2.512e-4), (4.107, 4.002e-3, 1.433e-2), (1.839, 1.218e-2, 0.4385),
             (1.958, 1.733e-1, 5.011)),
}
MATS = {"water": "water", "air": "air", "bone": BONE_ICRP, "soft": SOFT_ICRP}


@pytest.mark.parametrize("key", sorted(ESTAR))
def test_unrestricted_stopping_and_csda_range_match_estar(key):
    t = np.array(ENERGIES)
    ref = np.array(ESTAR[key])
    col = ex.collision_stopping_power(MATS[key], ex.ELECTRON, t)
    rad = ex.radiative_stopping_power(MATS[key], ex.ELECTRON, t)
    rng = ex.csda_range_g_cm2(MATS[key], t)
    np.testing.assert_allclose(col, ref[:, 0], rtol=3e-3)
    np.testing.assert_allclose(rad, ref[:, 1], rtol=3e-3)
    np.testing.assert_allclose(rng, ref[:, 2], rtol=3e-3)


def test_density_effect_of_water_matches_estar():
    # ESTAR water, density-effect parameter δ at 1 and 10 MeV; 0 below 0.5 MeV (insulator).
    d = ex.density_effect("water", np.array([0.3, 1.0, 10.0]))
    np.testing.assert_allclose(d, [0.0, 0.2428, 2.992], atol=2e-3)


@pytest.mark.parametrize(("material", "i_ev"), [(LUNG_ICRP, 75.3), (ADIPOSE_ICRP, 63.2),
                                                 (BONE_ICRP, 106.4), (MUSCLE_ICRP, 75.3),
                                                 (SOFT_ICRP, 72.3)])
def test_bragg_rule_reproduces_icru37_mean_excitation_energies(material, i_ev):
    # ICRU Report 37 (1984) Table 5.5 values, as used by ESTAR for these compositions.
    assert ex.mean_excitation_ev(material) == pytest.approx(i_ev, rel=5e-3)
    assert ex.mean_excitation_ev("water") == 75.0 and ex.mean_excitation_ev("air") == 85.7


def _zoa(material):
    return ex._medium(material).z_over_a


@pytest.mark.parametrize("t", [0.03, 0.3, 1.0, 10.0])
def test_restricted_plus_hard_moller_and_bhabha_loss_is_unrestricted(t):
    cut = 0.01
    tau = t / ex.ELECTRON_MASS_MEV
    beta2 = tau * (tau + 2.0) / (tau + 1.0) ** 2
    c = ex.BETHE_MEV_CM2_MOL * _zoa("water") / t
    g2, g3 = (tau / (tau + 1.0)) ** 2, (2.0 * tau + 1.0) / (tau + 1.0) ** 2

    def moller(e):  # Møller DCS dσ/dε [cm²/g] (PIRS-701 eq. 2.4.?)
        return c / beta2 * (1 / e**2 + 1 / (1 - e) ** 2 + g2 - g3 / (e * (1 - e)))

    y = 1.0 / (tau + 2.0)
    k = 1.0 - 2.0 * y
    b1, b2, b4 = 2.0 - y * y, k * (3.0 + y * y), k**3
    b3 = b4 + k * k

    def bhabha(e):
        return c * (1.0 / (beta2 * e * e) - b1 / e + b2 - b3 * e + b4 * e * e)

    for sp, dcs, top, sigma in ((ex.ELECTRON, moller, 0.5, ex.moller_cross_section),
                                (ex.POSITRON, bhabha, 1.0, ex.bhabha_cross_section)):
        full = ex.collision_stopping_power("water", sp, t)
        restricted = ex.collision_stopping_power("water", sp, t, cut)
        hard_loss = quad(lambda e, dcs=dcs: t * e * dcs(e), cut / t, top, limit=200)[0]
        assert (restricted + hard_loss) / full == pytest.approx(1.0, abs=1e-9)
        assert quad(dcs, cut / t, top, limit=200)[0] == pytest.approx(sigma("water", t, cut), rel=1e-9)


@pytest.mark.parametrize("t", [0.05, 1.0, 10.0])
def test_restricted_plus_hard_radiative_loss_is_estar_radiative(t):
    kc = 0.01
    z13, c = ex._brems_shape("cortical_bone")
    norm = quad(lambda k: ke.brems_chi(z13, c, t, k), 0.0, 1.0, limit=400)[0]
    s_rad = ex.radiative_stopping_power("cortical_bone", ex.ELECTRON, t)
    hard_loss = s_rad * quad(lambda k: ke.brems_chi(z13, c, t, k), kc / t, 1.0, limit=400)[0] / norm
    soft = ex.restricted_radiative_stopping_power("cortical_bone", ex.ELECTRON, t, kc)
    assert (soft + hard_loss) / s_rad == pytest.approx(1.0, abs=1e-4)
    number = s_rad / t * quad(lambda k: ke.brems_chi(z13, c, t, k) / k, kc / t, 1.0, limit=400)[0] / norm
    assert ex.hard_brems_cross_section("cortical_bone", ex.ELECTRON, t, kc) == pytest.approx(number,
                                                                                             rel=1e-4)


def test_positron_radiative_loss_is_below_electron():
    t = np.array([0.01, 1.0, 10.0])
    ratio = (ex.radiative_stopping_power("water", ex.POSITRON, t)
             / ex.radiative_stopping_power("water", ex.ELECTRON, t))
    assert np.all(ratio < 1.0) and np.all(np.diff(ratio) > 0) and ratio[-1] > 0.9


def test_heitler_total_is_the_integral_of_its_dcs():
    for t in (0.01, 1.0, 10.0):
        g = t / ex.ELECTRON_MASS_MEV + 1.0
        p = math.sqrt(g * g - 1.0)
        zmin = 1.0 / (g + 1.0 + p)

        def s(z, g=g):
            return -((g + 1.0) ** 2) + (g * g + 4.0 * g + 1.0) / z - 1.0 / z**2

        dcs = quad(lambda z, s=s: s(z) + s(1.0 - z), zmin, 0.5, limit=200)[0]
        per_electron = math.pi * ex.CLASSICAL_ELECTRON_RADIUS_CM**2 / ((g + 1.0) * (g * g - 1.0)) * dcs
        assert ex.heitler_cross_section("water", t) == pytest.approx(
            per_electron * ex.AVOGADRO * _zoa("water"), rel=1e-10)


# ELSEPA (Salvat, Jablonski & Powell, Comput. Phys. Commun. 165 (2005) 157; Dirac partial waves,
# the method of ICRU Report 77), first transport cross sections per atom [cm²] of H and O, as
# tabulated by ELSEPA 2020 runs in the wiscobolt project (files dcs_1p000e0{4,5,6,7}.dat).
ELSEPA_SIGMA1_CM2 = {0.01: (2.24458e-21, 1.11197e-19), 0.1: (3.39352e-23, 1.81433e-21),
                     1.0: (8.07500e-25, 4.51657e-23), 10.0: (1.77448e-26, 1.02967e-24)}


@pytest.mark.parametrize(("t", "tol"), [(0.01, 0.06), (0.1, 0.015), (1.0, 0.015), (10.0, 0.015)])
def test_transport_cross_section_of_water_matches_elsepa(t, tol):
    ours = 0.0  # the nuclear (Z²) part of our Z(Z + 1) screened Rutherford × Mott σ₁
    for z, w in ((1, 0.111894), (8, 0.888106)):
        ours += w * ex.lambda1_inverse(Material("el", ((z, 1.0),), 1.0, "test"), t) * z / (z + 1.0)
    h, o = ELSEPA_SIGMA1_CM2[t]
    elsepa = ex.AVOGADRO * (0.111894 / 1.00794 * h + 0.888106 / 15.9994 * o)
    assert ours == pytest.approx(elsepa, rel=tol)


@pytest.mark.parametrize("eta", [1e-6, 1e-3, 0.1, 1.0, 10.0])
def test_screened_rutherford_moments_match_quadrature(eta):
    """⟨1 − μ⟩ and ⟨(1 − μ)²⟩ of p(μ) ∝ (1 − μ + 2η)⁻² in closed form against quadrature."""
    norm = quad(lambda mu: (1 - mu + 2 * eta) ** -2, -1, 1, points=[1 - 2 * eta], limit=200)[0]
    m = [quad(lambda mu, k=k: (1 - mu) ** k * (1 - mu + 2 * eta) ** -2, -1, 1,
              points=[1 - 2 * eta], limit=200)[0] / norm for k in (1, 2)]
    m1, m2 = ex.wentzel_moments(eta)
    assert m1 == pytest.approx(m[0], rel=1e-7) and m2 == pytest.approx(m[1], rel=1e-6)


def test_second_transport_cross_section_of_water():
    """λ₁/λ₂ = 3 − (3/2)⟨t²⟩/⟨t⟩: close to 3 − 3/(ln(1/η) − 1) for MeV electrons (small η, about
    2.6 in water), rising towards 3 with energy; 1/λ₂ scales with 1/λ₁."""
    t = np.array([0.1, 1.0, 10.0])
    ratio = ex.lambda2_inverse("water", t) / ex.lambda1_inverse("water", t)
    assert np.all((ratio > 2.3) & (ratio < 2.9)) and np.all(np.diff(ratio) > 0)


@pytest.fixture(scope="module")
def tables():
    return ex.build_electron_tables(["water", "lung", "cortical_bone", "air"], cutoff_mev=0.1,
                                    photon_cutoff_mev=0.01, e_max_mev=20.0)


def test_tables_shape_grid_and_read_only(tables):
    n = tables.stopping.shape[2]
    assert n == math.ceil(math.log10(200.0) * ex.POINTS_PER_DECADE) + 1
    assert math.exp(tables.ln_e_min) == pytest.approx(0.1, rel=1e-14)
    assert math.exp(tables.ln_e_min + (n - 1) * tables.d_ln_e) == pytest.approx(20.0, rel=1e-12)
    for name in ("stopping", "range_g_cm2", "sigma_delta", "sigma_brems", "lambda1_inv",
                 "lambda2_inv"):
        arr = getattr(tables, name)
        assert arr.shape == (4, 2, n) and not arr.flags.writeable and arr.flags.c_contiguous
    assert tables.sigma_annih.shape == (4, n) and tables.brems_z13.shape == (4,)
    assert ex.build_electron_tables(["water", "lung", "cortical_bone", "air"], 0.1, 0.01, 20.0) is tables
    # Møller needs T > 2Δ; Bhabha and bremsstrahlung start above Δ and k_c
    t = np.exp(tables.ln_e_min + tables.d_ln_e * np.arange(n))
    assert np.all(tables.sigma_delta[:, 0, t <= 0.2] == 0.0)
    assert np.all(tables.sigma_delta[:, 0, t > 0.21] > 0)
    assert np.all(tables.sigma_delta[:, 1, 1:] > 0) and np.all(tables.sigma_brems[:, :, :] > 0)


def test_range_table_is_the_integral_of_the_stopping_table(tables):
    t = np.exp(tables.ln_e_min + tables.d_ln_e * np.arange(tables.stopping.shape[2]))
    for m in range(4):
        for sp in (0, 1):
            # trapezoid on the table's own nodes in ln T: an independent quadrature of ∫dT/L
            f = t / tables.stopping[m, sp]
            trap = np.concatenate(([0.0], np.cumsum(0.5 * (f[1:] + f[:-1]) * tables.d_ln_e)))
            # within the trapezoid rule's error h²/12·f''
            np.testing.assert_allclose(tables.range_g_cm2[m, sp, 1:], trap[1:], rtol=1e-4)
    # restricted loss < unrestricted, so the restricted range exceeds the CSDA range difference
    full = ex.csda_range_g_cm2("water", np.array([0.1, 10.0]))
    assert tables.range_g_cm2[0, 0, -1] > 0 and ke.range_of(tables, 0, 0, 10.0) > full[1] - full[0]


def test_kernel_lookups_interpolate_the_tables(tables):
    n = tables.stopping.shape[2]
    e = math.exp(tables.ln_e_min + 37.25 * tables.d_ln_e)
    i, f = ke.electron_position(tables, e)
    assert i == 37 and f == pytest.approx(0.25, abs=1e-9)
    assert ke.electron_position(tables, 1e-6) == (0, 0.0)
    assert ke.electron_position(tables, 1e3) == (n - 2, 1.0)
    s = ke.stopping_power(tables, 2, 1, e)
    assert s == pytest.approx(0.75 * tables.stopping[2, 1, 37] + 0.25 * tables.stopping[2, 1, 38], rel=1e-9)
    assert ke.stopping_power(tables, 0, 0, 1.0) == pytest.approx(
        ex.collision_stopping_power("water", 0, 1.0, 0.1)
        + ex.restricted_radiative_stopping_power("water", 0, 1.0, 0.01), rel=1e-4)
    sd, sb, sa = ke.hard_cross_sections(tables, 0, 1, 1.0)
    assert sd == pytest.approx(ex.bhabha_cross_section("water", 1.0, 0.1), rel=1e-4)
    assert sb == pytest.approx(ex.hard_brems_cross_section("water", 1, 1.0, 0.01), rel=1e-4)
    assert sa == pytest.approx(ex.heitler_cross_section("water", 1.0), rel=1e-4)
    assert ke.hard_cross_sections(tables, 0, 0, 1.0)[2] == 0.0


def test_energy_at_range_inverts_range_of(tables):
    for m in range(4):
        for sp in (0, 1):
            for e in (0.1, 0.1234, 0.7, 3.3, 19.9):
                r = ke.range_of(tables, m, sp, e)
                assert ke.energy_at_range(tables, m, sp, r) == pytest.approx(e, rel=1e-12)
            # CSDA loss over a small step matches ds·L
            r = ke.range_of(tables, m, sp, 5.0)
            s = 1e-4 * r
            loss = 5.0 - ke.energy_at_range(tables, m, sp, r - s)
            assert loss == pytest.approx(s * ke.stopping_power(tables, m, sp, 5.0), rel=2e-3)
    assert ke.energy_at_range(tables, 0, 0, -1.0) == pytest.approx(0.1, rel=1e-14)


def test_bad_input_raises_with_the_fix():
    with pytest.raises(PlanError, match="unknown material"):
        ex.build_electron_tables(["unobtainium"])
    with pytest.raises(OptionError, match="cut-off"):
        ex.build_electron_tables(["water"], cutoff_mev=0.0005)
    with pytest.raises(OptionError, match="cut-off"):
        ex.build_electron_tables(["water"], cutoff_mev=0.5, e_max_mev=0.2)
    with pytest.raises(PlanError, match="Z must be 1…98"):  # beyond the ESTAR and XCOM data
        ex.build_electron_tables([Material("es", ((99, 1.0),), 1.0, "test")])
