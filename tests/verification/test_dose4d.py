"""4D dose: static anatomy must accumulate to the single-phase dose, by all three methods."""

import json

import numpy as np
import pytest

from tetdose.cli import main
from tetdose.core.image import Image
from tetdose.core.io import read_image, read_mesh, write_image, write_mesh
from tetdose.core.transfer import mesh_dose_to_grid
from tetdose.dose.dose4d import run_dose4d, write_dose4d
from tetdose.motion.phases import PhaseSeries
from tetdose.transport import PhotonSource, Plan, TransportSettings, simulate

from helpers import box_mesh, grid_for

GRID = grid_for([0, 0, 0], [40, 40, 40], [5, 5, 5])
PLAN = Plan((PhotonSource("parallel", [20, 20, -100], [0, 0, 1], energies_mev=[1.25],
                          field_mm=[20, 20]),))


def water_mesh():
    """Water box meshed on the CT's voxel planes (6 tets per voxel): matched geometry."""
    m = box_mesh([0, 0, 0], [40, 40, 40], (8, 8, 8))
    return m.with_data(point_data={"density": np.full(m.n_points, 1.0)})


def static_series(n_phases=3):
    ref = water_mesh()
    pts = np.repeat(ref.points_mm[None], n_phases, axis=0)
    return PhaseSeries(ref, pts, np.linspace(0, 100, n_phases, endpoint=False)).with_density(
        np.repeat(ref.point_data["density"][None], n_phases, axis=0))


def ct_water():
    return Image(np.zeros(GRID.shape, dtype=np.int16), GRID)  # 0 HU ≈ 1.0 g/cm³ (Schneider)


@pytest.fixture(scope="module")
def static_run():
    settings = TransportSettings(n_histories=20_000, n_batches=10, seed=5, physics="kerma")
    return run_dose4d(static_series(), PLAN, settings, ct_hu=ct_water()), settings


def test_static_accumulation_equals_single_phase_in_distribution(static_run):
    run, settings = static_run
    single = simulate(run.series.mesh(0), PLAN,
                      TransportSettings(n_histories=60_000, n_batches=10, seed=77, physics="kerma"))
    acc = run.accumulated
    # The tets inside the 20 × 20 mm field (not those above a threshold on one run's dose: the
    # noise that lifts a tet over it would bias that run's side of the z-scores).
    hot = np.all(np.abs(run.series.mesh(0).centroids_mm[:, :2] - 20.0) < 8.0, axis=1)
    z = (acc.dose_gy - single.dose_gy)[hot] / np.hypot(acc.dose_std_gy, single.dose_std_gy)[hot]
    assert np.abs(z).max() < 5.0
    assert abs(z.mean()) < 4.0 / np.sqrt(hot.sum()) + 0.3
    # Mass is conserved per tet in every phase, so the accumulation is a plain weighted mean.
    np.testing.assert_allclose(acc.dose_gy, np.mean([r.mesh_part().dose_gy for r in run.results], axis=0),
                               rtol=1e-12)


def test_three_accumulations_agree_on_static_anatomy(static_run):
    run, _ = static_run
    vox = run.voxel
    mean_voxel = np.mean([d.array for d in vox.doses], axis=0)
    # No motion: both voxel methods reduce to the mean of the phase doses, exactly.
    np.testing.assert_allclose(vox.direct_mapping.array, mean_voxel, rtol=1e-9, atol=1e-30)
    np.testing.assert_allclose(vox.energy_mass_transfer.array, mean_voxel, rtol=1e-9, atol=1e-30)
    # Mesh accumulation (energy-conserving resampling to the grid) vs voxel: the mesh follows
    # the voxel planes, so both estimate the same voxel dose; compare with z-scores.
    mesh_on_grid = mesh_dose_to_grid(run.series.reference, run.accumulated.dose_gy, GRID).array
    var_mesh = mesh_dose_to_grid(run.series.reference, run.accumulated.dose_std_gy**2 * 6, GRID)
    var_vox = np.mean([r.to_images()[1].array ** 2 for r in vox.results], axis=0) / 3
    hot = mean_voxel > 0.05 * mean_voxel.max()
    z = (mesh_on_grid - mean_voxel)[hot] / np.sqrt(var_mesh.array + var_vox)[hot]
    assert np.abs(z).max() < 5.0
    assert abs(z.mean()) < 0.5


def test_write_dose4d_outputs(static_run, tmp_path):
    run, _ = static_run
    out = write_dose4d(run, tmp_path / "dose4d")
    acc = read_mesh(out / "accumulated.vtu")
    np.testing.assert_allclose(acc.cell_data["dose"], run.accumulated.dose_gy)
    assert len(list(out.glob("phase_*.vtu"))) == 3 and len(list(out.glob("phase_*.json"))) == 3
    record = json.loads((out / "phase_000.0.json").read_text())
    led = record["ledger"]
    assert led["source_mev"] == pytest.approx(led["deposited_mev"] + led["escaped_mev"]
                                              + led["cutoff_mev"] + led["lost_mev"], rel=1e-9)
    assert read_image(out / "voxel" / "accumulated_energy_mass_transfer.nrrd").grid.same_as(GRID)


def test_cli_deform_then_dose4d(tmp_path):
    write_mesh(tmp_path / "mapped.vtu", water_mesh())
    write_image(tmp_path / "ct.nrrd", ct_water())
    (tmp_path / "plan.toml").write_text(
        '[[beam]]\ntype = "parallel"\nenergy_mev = 1.25\nposition_mm = [20.0, 20.0, -100.0]\n'
        'direction = [0.0, 0.0, 1.0]\nfield_mm = [20.0, 20.0]\n')
    assert main(["deform", "-q", "--mesh", str(tmp_path / "mapped.vtu"), "--breathing",
                 "--n-phases", "3", "--amplitude-mm", "4", "-o", str(tmp_path / "phases")]) == 0
    assert main(["dose4d", "--physics", "kerma", "-q", "--phases", str(tmp_path / "phases"), "--plan",
                 str(tmp_path / "plan.toml"), "--histories", "4000", "--batches", "4",
                 "--like", str(tmp_path / "ct.nrrd"), "-o", str(tmp_path / "dose4d")]) == 0
    acc = read_mesh(tmp_path / "dose4d" / "accumulated.vtu")
    assert acc.cell_data["dose"].max() > 0 and np.all(acc.cell_data["dose_std"] >= 0)
    summary = json.loads((tmp_path / "dose4d" / "summary.json").read_text())
    assert len(summary["phases"]) == 3
    assert all(p["lost_photons"] == 0 for p in summary["phases"])
