"""Dose to water: s_w,m per medium for 6 MV against Siebers et al. (2000) (the per-medium table),
and a run's per-cell conversion from the electron fluence it tracked, in tets and voxels (same
seed: D_w / D_m is each cell's tracked s_w,m exactly, and water gives exactly 1)."""

import numpy as np
import pytest

from tetdose.core.mesh import TetMesh
from tetdose.errors import PlanError
from tetdose.plan.spectra import named_spectrum
from tetdose.transport import PhotonSource, Plan, TransportSettings, World, simulate
from tetdose.transport.history._electron import L_E_CUTOFF, L_E_DEPOSITED
from tetdose.transport.physics.dose_to_water import water_to_medium_ratio
from tetdose.transport.physics.materials import resolve_material
from tetdose.transport.run.job import build_job, cross_sections, run_batches

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


def _world(geometry: str, rho_of_z, label_of_z) -> World:
    """A 40 mm cube of 8 mm voxels or of 2 × 2 × 4 boxes of tets; density and region label
    (→ the plan's materials) as functions of z [mm]."""
    if geometry == "voxels":
        grid = grid_for([-20, -20, -20], [20, 20, 20], [8.0, 8.0, 8.0])
        rho = density_image(grid, lambda x, y, z: rho_of_z(z))
        labels = density_image(grid, lambda x, y, z: label_of_z(z))
        return World(density=rho, labels=labels.with_array(labels.array.astype(np.int32)))
    mesh = box_mesh([-20, -20, -20], [20, 20, 20], (2, 2, 4))
    region = label_of_z(mesh.centroids_mm[:, 2]).astype(np.int32)
    return World(mesh=TetMesh(mesh.points_mm, mesh.tets, region,
                              {"density": rho_of_z(mesh.points_mm[:, 2]).astype(float)}))


def _run(world: World, materials: dict, dose_to: str, n: int = 300, **settings):
    e, w = named_spectrum("6MV")
    beam = PhotonSource("parallel", [0.0, 0.0, -40.0], [0, 0, 1], energies_mev=e, line_weights=w,
                        field_mm=[30.0, 30.0])
    return simulate(world, Plan((beam,), materials=materials),
                    TransportSettings(n, 4, 7, dose_to=dose_to, **settings), progress=False)


@pytest.mark.parametrize("geometry", ["voxels", "tets"])
def test_water_world_gives_dose_to_water_equal_to_dose_to_medium_bit_for_bit(geometry):
    world = _world(geometry, lambda z: np.full(np.shape(z), 1.0), lambda z: np.ones(np.shape(z)))
    dm, dw = (_run(world, {1: "water"}, to) for to in ("medium", "water"))
    assert np.count_nonzero(dm.dose_gy) > 5
    np.testing.assert_array_equal(dw.energy_per_batch_mev, dm.energy_per_batch_mev)
    rec = dw.extra["dose_to_water"]
    assert rec["s_w_m"] == {"water": 1.0} and "tracked" in rec["method"]
    assert np.all(dw.water_ratio == 1.0) and dm.water_ratio is None


# ICRP cortical bone, ICRU soft tissue and lung at their densities, one medium per world
# (Siebers et al.'s 6 MV ratios above); each is checked against the per-medium table too.
HOMOGENEOUS = {"icrp_cortical_bone": 1.85, "soft_tissue": 1.06, "lung": 0.26}


@pytest.mark.parametrize("geometry", ["voxels", "tets"])
@pytest.mark.parametrize("medium", sorted(HOMOGENEOUS))
def test_fluence_averaged_ratio_of_a_homogeneous_world_agrees_with_siebers_and_the_table(
        geometry, medium):
    rho = HOMOGENEOUS[medium]
    world = _world(geometry, lambda z: np.full(np.shape(z), rho), lambda z: np.ones(np.shape(z)))
    dm, dw = (_run(world, {1: medium}, to) for to in ("medium", "water"))
    rec = dw.extra["dose_to_water"]
    s = rec["s_w_m"][resolve_material(medium).name]
    lo, hi = SIEBERS_6MV[medium]
    assert lo * 0.99 <= s <= hi * 1.01
    assert s == pytest.approx(water_to_medium_ratio(medium), rel=0.01)
    assert rec["cells_fallback"] < rec["cells_dosed"]
    hit = dm.dose_gy > 0
    # the same histories: D_w = D_m · s_w,m of each cell, exactly that factor
    np.testing.assert_allclose(dw.dose_gy[hit] / dm.dose_gy[hit], dw.water_ratio[hit], rtol=1e-12)
    np.testing.assert_array_equal(dw.ledger_per_batch_mev, dm.ledger_per_batch_mev)
    np.testing.assert_array_equal(dw.counts_per_batch, dm.counts_per_batch)


@pytest.mark.parametrize("settings", [{}, {"photon_splitting": 4, "splitting_scheme": "repeat"},
                                      {"range_rejection_mev": 0.0}])
def test_every_electron_path_adds_its_energy_to_the_medium_sum(settings):
    """B sums wt·s·L_m over the steps (≈ the continuous loss) plus the track ends (part of the
    cut-off energy): analog, replayed (repeat) and range-rejected tracks alike; their
    fluence-averaged ratios agree with the table; the sums change no particle's path."""
    world = _world("voxels", lambda z: np.full(np.shape(z), 1.85), lambda z: np.ones(np.shape(z)))
    e, w = named_spectrum("6MV")
    beam = PhotonSource("parallel", [0.0, 0.0, -40.0], [0, 0, 1], energies_mev=e, line_weights=w,
                        field_mm=[30.0, 30.0])
    plan = Plan((beam,), materials={1: "icrp_cortical_bone"})
    rows = {}
    for to in ("medium", "water"):
        st = TransportSettings(600, 2, 7, dose_to=to, **settings)
        job, _ = build_job(world, plan, st)
        rows[to] = run_batches(job, cross_sections(job, st), st, 0, 2)
    assert rows["medium"][3].size == 0  # dose to medium tallies no sums and the same particles
    for medium, water in zip(rows["medium"][:3], rows["water"][:3], strict=True):
        np.testing.assert_array_equal(medium, water)
    _, ledger, _, sums = rows["water"]
    a, b = sums.sum(axis=(0, 2))
    led = ledger.sum(axis=0)
    assert 0.99 * led[L_E_DEPOSITED] < b < led[L_E_DEPOSITED] + led[L_E_CUTOFF]
    assert a / b == pytest.approx(water_to_medium_ratio("icrp_cortical_bone"), rel=0.01)


@pytest.mark.parametrize("geometry", ["voxels", "tets"])
def test_each_cell_gets_the_ratio_of_its_own_fluence(geometry):
    """Bone above z = 0, water below: water cells exactly 1, bone cells ≈ 1.11; the per-cell
    ratios go to VTU (tets) and the per-medium fallback is recorded."""
    world = _world(geometry, lambda z: np.where(z > 0.0, 1.85, 1.0),
                   lambda z: np.where(z > 0.0, 2, 1))
    dw = _run(world, {1: "water", 2: "icrp_cortical_bone"}, "water")
    rec = dw.extra["dose_to_water"]
    assert set(rec["fallback"]["s_w_m"]) == {"water", "icrp_cortical_bone"}
    mats = np.array(dw.extra["materials"])
    z = (world.mesh.centroids_mm[:, 2] if geometry == "tets"
         else world.density.grid.voxel_centers_mm()[:, 2])
    hit = dw.dose_gy > 0
    water = hit & (z < 0)
    bone = hit & (z > 0)
    assert water.sum() > 2 and bone.sum() > 2 and list(mats) == ["water", "icrp_cortical_bone"]
    assert np.all(dw.water_ratio[water] == 1.0)
    assert np.all((dw.water_ratio[bone] > 1.09) & (dw.water_ratio[bone] < 1.13))
    if geometry == "tets":
        assert np.array_equal(dw.to_mesh(world.mesh).cell_data["s_w_m"], dw.water_ratio)


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


def test_hybrid_combined_dose_to_water_is_the_combined_dose_to_medium_times_its_ratio():
    """Mesh (bone) inside a CT (water-like soft tissue): on the CT grid, D_w = D_m · s_w,m with
    s_w,m of each voxel the energy-weighted one of the voxel and the tets overlapping it."""
    grid = grid_for([-20, -20, -20], [20, 20, 20], [8.0, 8.0, 8.0])
    mesh = box_mesh([-10, -10, -10], [10, 10, 10], (2, 2, 2))
    mesh = TetMesh(mesh.points_mm, mesh.tets, np.full(mesh.n_tets, 2, np.int32),
                   {"density": np.full(mesh.n_points, 1.85)})
    world = World(mesh=mesh, density=density_image(grid, lambda x, y, z: np.full(x.shape, 1.0)))
    dm, dw = (_run(world, {2: "icrp_cortical_bone"}, to) for to in ("medium", "water"))
    cm, cw = dm.combined(), dw.combined()
    hit = cm.dose_gy > 0
    assert hit.sum() > 5 and np.ptp(cw.water_ratio[hit]) > 0.05  # bone and soft tissue voxels
    np.testing.assert_allclose(cw.dose_gy[hit], cm.dose_gy[hit] * cw.water_ratio[hit], rtol=1e-12)
    np.testing.assert_array_equal(dw.voxel_part().water_ratio, dw.water_ratio[dw.n_tets:])
