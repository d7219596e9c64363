"""The built-in composition library: the publications' media counts, every medium's photon and
electron data finite, the tables' sums, and spot checks against independent references (NIST
SRD 126 compound tables, the ICRU 44 media of NIST's Table 2, ESTAR water)."""

import json
import re
from collections import Counter
from importlib import resources
from pathlib import Path

import numpy as np
import pytest

from tetdose.core.composition import SUM_TOLERANCE
from tetdose.errors import PlanError
from tetdose.transport.physics import electron_xs as ex
from tetdose.transport.physics.materials import MATERIALS, resolve_material
from tetdose.transport.physics.xs import mass_coefficients

NIST_DIR = Path(__file__).resolve().parents[2] / ".." / "shared" / "reference" / "nist"
RAW = json.loads(resources.files("tetdose.transport.physics").joinpath(
    "data/compositions.json").read_text())


def _names(prefix: str) -> list[str]:
    return [n for n in RAW["materials"] if n.startswith(prefix)]


@pytest.mark.parametrize("sex", ["m", "f"])
def test_icrp110_has_the_53_media_of_each_phantom(sex):
    names = _names(f"icrp110_{sex}_")
    assert len(names) == 53 == RAW["counts"][f"icrp110_{sex}"]  # ICRP 110 Annex B, Tables B.1/B.2
    numbers = Counter(int(re.search(r"medium (\d+)", RAW["materials"][n]["source"]).group(1))
                      for n in names)
    assert sorted(numbers) == list(range(1, 54)) and set(numbers.values()) == {1}


def test_icru46_lists_the_adult_and_age_independent_tissues_of_table_a1():
    names = _names("icru46_")
    assert len(names) == RAW["counts"]["icru46"] == 62
    assert all("ICRU Report 46" in RAW["materials"][n]["source"] for n in names)


def test_earlier_icrp110_names_are_the_male_media():
    for alias, target in RAW["aliases"].items():
        a, b = MATERIALS[alias], MATERIALS[target]
        assert target.startswith("icrp110_m_") and a.name == alias
        assert (a.mass_fractions, a.density_g_cm3) == (b.mass_fractions, b.density_g_cm3)


def test_every_entry_sums_to_one_and_records_a_normalised_table():
    for name, d in RAW["materials"].items():
        total = sum(d["composition"].values())
        assert abs(total - 1.0) < 1e-5, name  # stored normalised (to 6 decimals)
        assert d["density_g_cm3"] > 0.0
        if "table_sum" in d:  # the publication's own rounding: recorded, and said in the source
            assert abs(d["table_sum"] - 1.0) <= SUM_TOLERANCE + 1e-12 and "normalised" in d["source"]
    assert RAW["materials"]["icrp110_f_cervical_spine_spongiosa"]["table_sum"] == 1.001


def test_every_medium_has_finite_photon_and_electron_data():
    e = np.array([0.03, 1.0, 10.0])
    for name in MATERIALS:
        mu, mu_en = mass_coefficients(name, e)
        s_col = ex.collision_stopping_power(name, ex.ELECTRON, e)
        assert np.all(np.isfinite(mu)) and np.all(mu.sum(axis=1) > 0.0), name
        assert np.all(np.isfinite(mu_en)) and np.all(mu_en > 0.0), name
        assert np.all(np.isfinite(s_col)) and np.all(s_col > 0.0), name


# ICRU 46 tissues taken unchanged from ICRU 44 against the ICRU 44 media of NIST SRD 126 Table 2
# (another transcription of the same tables) and NIST's compound μ/ρ, μen/ρ tables for them.
TWINS = {"icru46_muscle": ("muscle", "muscle.csv"), "icru46_blood": ("blood", "blood.csv"),
         "icru46_adipose_2": ("adipose", "adipose.csv"), "icru46_lung": ("lung", "lung.csv"),
         "icru46_cortical_bone": ("cortical_bone", "bone.csv")}


@pytest.mark.parametrize("name", sorted(TWINS))
def test_icru46_tissues_from_icru44_match_nist_table_2_and_its_attenuation(name):
    twin, table = TWINS[name]
    assert MATERIALS[name].mass_fractions == MATERIALS[twin].mass_fractions
    if not NIST_DIR.exists():
        pytest.skip(f"NIST reference tables not found at {NIST_DIR} (../shared beside the checkout)")
    t = np.loadtxt(NIST_DIR / table, delimiter=",", comments="#")
    e = np.array([0.015, 0.03, 0.05, 0.1, 0.3, 1.0, 3.0, 10.0, 20.0])  # NIST table nodes
    rows = np.searchsorted(t[:, 0], e)
    assert np.allclose(t[rows, 0], e)
    mu_ref, mu_en_ref = t[rows, 1], t[rows, 2]
    mu, mu_en = mass_coefficients(name, e)
    np.testing.assert_allclose(mu.sum(axis=1), mu_ref, rtol=0.006)
    np.testing.assert_allclose(mu_en, mu_en_ref, rtol=0.01)


def test_a_library_medium_by_composition_reproduces_estar_water():
    # ICRU 46's water (H 0.112, O 0.888), I from ICRU 37's Bragg rule, not the named water's 75 eV
    t = np.array([0.01, 0.1, 1.0, 10.0])
    estar = np.array([22.56, 4.115, 1.849, 1.968])  # NIST ESTAR water, collision [MeV cm²/g]
    assert "icru46_water" not in ex._NAMED_I_EV
    np.testing.assert_allclose(ex.collision_stopping_power("icru46_water", ex.ELECTRON, t), estar,
                               rtol=3e-3)


def test_an_unknown_name_is_refused_with_the_closest_library_names():
    with pytest.raises(PlanError, match=r"closest: icrp110_m_kidneys"):
        resolve_material("icrp110_m_kidney")
