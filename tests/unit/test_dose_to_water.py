"""Dose to water: s_w,m per medium for 6 MV against Siebers et al. (2000), and the conversion of a
run's dose in tets and voxels (same seed: D_w / D_m is each cell's medium's s_w,m exactly)."""

import numpy as np
import pytest

from tetdose.errors import PlanError
from tetdose.transport import PhotonSource, Plan, TransportSettings, World, simulate
from tetdose.transport.physics.dose_to_water import water_to_medium_ratio

from helpers import box_mesh, density_image, grid_for

# Siebers, Keall, Nahum & Mohan, Phys. Med. Biol. 45:983 (2000), 6 MV: cortical bone ≈ 1.11,
# soft tissues 1.00–1.02, lung ≈ 1.00 (issue 32's reading of the paper's Table 2).
SIEBERS_6MV = {"icrp_cortical_bone": (1.11, 1.11), "soft_tissue": (1.00, 1.02),
               "muscle": (1.00, 1.02), "icrp_soft_tissue": (1.00, 1.02), "blood": (1.00, 1.02),
               "lung": (1.00, 1.00), "icrp_lung": (1.00, 1.00)}


@pytest.mark.parametrize("name", sorted(SIEBERS_6MV))
def test_ratio_per_medium_agrees_with_siebers_within_one_percent(name):
    lo, hi = SIEBERS_6MV[name]
    s = water_to_medium_ratio(name)
    assert lo * 0.99 <= s <= hi * 1.01


def test_water_is_exactly_one_and_bone_is_above_ten_percent():
    assert water_to_medium_ratio("water") == 1.0
    assert water_to_medium_ratio("cortical_bone") > 1.10  # ICRU 44 bone, 1.92 g/cm³


def _plan() -> Plan:
    src = PhotonSource("parallel", [0.0, 0.0, -30.0], [0, 0, 1], energies_mev=np.array([1.25]),
                       line_weights=np.ones(1), field_mm=[16.0, 16.0])
    return Plan((src,))


@pytest.mark.parametrize("geometry", ["voxels", "tets"])
def test_dose_to_water_is_dose_to_medium_times_the_cell_medium_ratio(geometry):
    if geometry == "voxels":
        grid = grid_for([-10, -10, -10], [10, 10, 10], [4.0, 4.0, 4.0])
        world = density_image(grid, lambda x, y, z: np.where(z > 0.0, 1.85, 1.0))
    else:
        mesh = box_mesh([-10, -10, -10], [10, 10, 10], (3, 3, 4))
        rho = np.where(mesh.points_mm[:, 2] > 0.0, 1.85, 1.0)
        world = World(mesh=mesh.with_data(point_data={"density": rho}))
    runs = {to: simulate(world, _plan(), TransportSettings(400, 4, 7, dose_to=to,
                                                           electron_cutoff_mev=0.5),
                         progress=False) for to in ("medium", "water")}
    dm, dw = runs["medium"], runs["water"]
    assert dm.extra["dose_to"] == "medium" and dw.extra["dose_to"] == "water"
    ratios = dw.extra["dose_to_water"]["s_w_m"]
    assert set(ratios) == set(dw.extra["materials"]) and "Siebers" in dw.extra["dose_to_water"][
        "method"]
    hit = dm.dose_gy > 0
    assert hit.sum() > 5
    got = dw.dose_gy[hit] / dm.dose_gy[hit]
    expected = {round(v, 12) for v in ratios.values()}
    assert {round(v, 12) for v in got} <= expected
    assert len({round(v, 12) for v in got}) >= 2  # bone and soft tissue both hit
    np.testing.assert_allclose(dw.dose_std_gy[hit] / dm.dose_std_gy[hit], got, rtol=1e-9)


def test_dose_to_water_needs_dose_physics():
    with pytest.raises(PlanError, match="dose_to 'ink'"):
        TransportSettings(10, 2, dose_to="ink")
    with pytest.raises(PlanError, match="physics='dose' with dose_to='water'"):
        TransportSettings(10, 2, physics="kerma", dose_to="water")


def test_vtu_flag_and_records_say_which_dose_it_is(tmp_path):
    from tetdose.core.io import read_mesh, write_mesh
    from tetdose.dose.dose_to import ARRAY, mark, recorded_dose_to, require_same
    from tetdose.errors import OptionError

    mesh = box_mesh([0, 0, 0], [2, 2, 2], (1, 1, 1))
    write_mesh(tmp_path / "w.vtu", mark(mesh.with_data(cell_data={"dose": np.ones(mesh.n_tets)}),
                                        "water"))
    back = read_mesh(tmp_path / "w.vtu")
    assert np.all(back.cell_data[ARRAY] == 1)
    assert recorded_dose_to(tmp_path / "w.vtu", back) == "water"  # no record: the VTU flag
    (tmp_path / "w.json").write_text('{"dose_to": "medium"}')
    assert recorded_dose_to(tmp_path / "w.vtu", back) == "medium"  # the record wins
    assert recorded_dose_to(tmp_path / "none.nrrd") == "medium"
    assert require_same(None, "water", "x") == "water"
    with pytest.raises(OptionError, match="x is dose to water, not to medium"):
        require_same("medium", "water", "x")
