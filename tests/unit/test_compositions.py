"""Compositions by name: plan.toml [materials.NAME] tables, the built-in library against NIST
(elemental μ/ρ, μen/ρ mixed by weight; ESTAR stopping powers), nominal densities, the run record."""

import tomllib
from pathlib import Path

import numpy as np
import pytest

from tetdose.core.composition import Material, material_from_symbols
from tetdose.errors import PlanError
from tetdose.plan.model import Plan
from tetdose.transport.physics import electron_xs as ex
from tetdose.transport.physics.materials import LUNG_NOMINAL_G_CM3, MATERIALS
from tetdose.transport.physics.xs import mass_coefficients
from tetdose.transport.run.job import media_record, plan_media

NIST_DIR = Path(__file__).resolve().parents[2] / ".." / "shared" / "reference" / "nist"
BONE = ("H = 0.047234, C = 0.14433, N = 0.04199, O = 0.446096, Mg = 0.0022, P = 0.10497, "
        "S = 0.00315, Ca = 0.20993, Zn = 0.0001")
PLAN = """
[[beam]]
type = "point"
energy_mev = 1.0
position_mm = [0.0, 0.0, -100.0]
[materials]
1 = "water"
2 = "my_bone"
[materials.my_bone]
composition = {{ {comp} }}
density = {rho}
{extra}
"""


def _plan(comp: str = BONE, rho: float = 1.85, extra: str = "") -> Plan:
    return Plan.from_dict(tomllib.loads(PLAN.format(comp=comp, rho=rho, extra=extra)))


def test_plan_table_defines_a_named_composition():
    plan = _plan(extra="mean_excitation_ev = 106.4")
    assert plan.materials == {1: "water", 2: "my_bone"}
    mine = plan.compositions["my_bone"]
    assert mine.density_g_cm3 == 1.85 and mine.mean_excitation_ev == 106.4
    assert mine.mass_fractions == MATERIALS["icrp_cortical_bone"].mass_fractions
    media = plan_media(["water", "my_bone"], plan)
    assert media[0] == "water" and media[1] is mine
    rec = media_record(media)
    assert rec["materials"] == ["water", "my_bone"]
    assert rec["compositions"]["my_bone"]["composition"]["Ca"] == 0.20993
    assert rec["compositions"]["my_bone"]["density_g_cm3"] == 1.85


def test_same_composition_by_plan_and_by_library_gives_the_same_electron_data():
    mine = _plan(extra="mean_excitation_ev = 106.4").compositions["my_bone"]
    t = np.array([0.1, 1.0, 10.0])
    np.testing.assert_array_equal(ex.collision_stopping_power(mine, ex.ELECTRON, t),
                                  ex.collision_stopping_power("icrp_cortical_bone", ex.ELECTRON, t))


@pytest.mark.parametrize(("comp", "extra", "match"), [
    ("H = 0.5, O = 0.4", "", "sum to 0.900000, not 1"),
    ("H = 0.1119, Xx = 0.8881", "", "'Xx' is not an element symbol"),
    ("H = 0.1119, O = 0.8881", "mean_excitation_ev = 2.0", "not a mean excitation energy"),
    ("H = 0.1119, O = 0.8881", "colour = 1", "unknown key"),
])
def test_bad_tables_are_refused_with_the_fix(comp, extra, match):
    with pytest.raises(PlanError, match=match):
        _plan(comp, extra=extra)


def test_a_table_under_a_region_label_and_an_unknown_name_are_refused():
    with pytest.raises(PlanError, match=r"define the composition as \[materials.NAME\]"):
        Plan.from_dict(tomllib.loads(PLAN.format(comp=BONE, rho=1.85, extra="").replace(
            "[materials.my_bone]", "[materials.3]")))
    with pytest.raises(PlanError, match="unknown material 'unobtainium'"):
        plan_media(["unobtainium"], _plan())


def test_library_entries_are_valid_and_cite_their_source():
    assert len(MATERIALS) >= 40
    for name, m in MATERIALS.items():
        assert m.name == name and len(m.source) > 10
        assert abs(m.weights.sum() - 1.0) < 1e-12
    assert MATERIALS["lung"].density_g_cm3 == LUNG_NOMINAL_G_CM3 == 0.26
    assert MATERIALS["icrp_lung"].density_g_cm3 == 0.26


def _nist_mixture(m: Material, e: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """μ/ρ and μen/ρ [cm²/g] mixed by weight from NIST's elemental tables (elements without a
    table here, e.g. Zn at 1e-4, are left out and the rest renormalised)."""
    mu, mu_en, total = np.zeros(e.size), np.zeros(e.size), 0.0
    for z, w in zip(m.elements, m.weights, strict=True):
        path = NIST_DIR / f"z{int(z):02d}.csv"
        if not path.exists():
            assert w < 1e-3, f"no NIST table for Z = {z}"
            continue
        t = np.loadtxt(path, delimiter=",", comments="#")
        total += w
        mu += w * np.exp(np.interp(np.log(e), np.log(t[:, 0]), np.log(t[:, 1])))
        mu_en += w * np.exp(np.interp(np.log(e), np.log(t[:, 0]), np.log(t[:, 2])))
    return mu / total, mu_en / total


@pytest.mark.parametrize("name", ["icrp_cortical_bone", "icrp_soft_tissue", "icrp_lung",
                                  "icrp110_mineral_bone", "icrp110_f_teeth", "icrp110_f_lung",
                                  "icru46_cranium", "icru46_hydroxyapatite", "pmma", "polystyrene",
                                  "solid_water"])
def test_library_photon_data_match_nist_elemental_tables_mixed(name):
    if not NIST_DIR.exists():
        pytest.skip(f"NIST reference tables not found at {NIST_DIR} (../shared beside the checkout)")
    e = np.array([0.015, 0.03, 0.05, 0.1, 0.3, 1.0, 3.0, 10.0, 20.0])  # NIST table nodes
    mu_ref, mu_en_ref = _nist_mixture(MATERIALS[name], e)
    mu, mu_en = mass_coefficients(name, e)
    np.testing.assert_allclose(mu.sum(axis=1), mu_ref, rtol=0.006)
    np.testing.assert_allclose(mu_en, mu_en_ref, rtol=0.01)


# NIST ESTAR (SRD 124), "Bone, Cortical (ICRP)" and "Tissue, Soft (ICRP)": collision and radiative
# stopping powers [MeV cm²/g] at 0.01, 0.1, 1, 10 MeV (the values of tests/unit/test_electron_xs.py).
ESTAR = {"icrp_cortical_bone": ((19.72, 3.679, 1.659, 1.799), (5.461e-3, 6.356e-3, 1.824e-2, 2.476e-1)),
         "icrp_soft_tissue": ((22.57, 4.107, 1.839, 1.958), (3.680e-3, 4.002e-3, 1.218e-2, 1.733e-1))}


@pytest.mark.parametrize("name", sorted(ESTAR))
def test_library_stopping_powers_match_estar(name):
    t = np.array([0.01, 0.1, 1.0, 10.0])
    col, rad = ESTAR[name]
    np.testing.assert_allclose(ex.collision_stopping_power(name, ex.ELECTRON, t), col, rtol=3e-3)
    np.testing.assert_allclose(ex.radiative_stopping_power(name, ex.ELECTRON, t), rad, rtol=3e-3)


def test_density_effect_is_taken_at_the_nominal_density():
    lung = MATERIALS["lung"]
    dense = material_from_symbols("lung_105", {"H": 0.103, "C": 0.105, "N": 0.031, "O": 0.749,
                                               "Na": 0.002, "P": 0.002, "S": 0.003, "Cl": 0.003,
                                               "K": 0.002}, 1.05, "test")
    assert dense.mass_fractions == lung.mass_fractions
    t = np.array([1.0, 10.0])
    d_lung, d_dense = ex.density_effect(lung, t), ex.density_effect(dense, t)
    assert np.all(d_lung < d_dense) and d_lung[1] > 0.0  # 0 at 1 MeV: below its threshold
    s_lung = ex.collision_stopping_power(lung, ex.ELECTRON, t)
    s_dense = ex.collision_stopping_power(dense, ex.ELECTRON, t)
    # S = K (Z/A)/β² · (B − δ): only δ differs, so ΔS/S = Δδ/(B − δ)
    np.testing.assert_allclose((s_lung - s_dense) / s_dense,
                               (d_dense - d_lung) / _bracket(dense, t), rtol=1e-9)


def _bracket(m: Material, t: np.ndarray) -> np.ndarray:
    tau = t / ex.ELECTRON_MASS_MEV
    beta2 = tau * (tau + 2.0) / (tau + 1.0) ** 2
    return ex.collision_stopping_power(m, ex.ELECTRON, t) * beta2 / (
        ex.BETHE_MEV_CM2_MOL * ex._medium(m).z_over_a)
