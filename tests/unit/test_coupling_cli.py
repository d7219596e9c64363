"""``--engine ompmc`` of ``tetdose dose`` and ``tetdose dose4d``: outputs, the mesh dose by energy,
the accumulation over phases, and the refusals (one line, exit 2)."""

import json

import numpy as np
import pytest

from tetdose.cli import main
from tetdose.core.calibration import HUCalibration
from tetdose.core.image import Image
from tetdose.core.io import read_image, read_mesh, write_image, write_mesh
from tetdose.coupling.ompmc import OmpmcOptions, phase_engine
from tetdose.coupling.onto_mesh import voxel_dose_onto_mesh
from tetdose.dose.dose4d import run_dose4d
from tetdose.motion.phases import PhaseSeries
from tetdose.transport import PhotonSource, Plan, TransportSettings

from helpers import box_mesh, grid_for

pytest.importorskip("ompmc", reason="ompmc (tetdose[ompmc]) is not installed")

GRID = grid_for([0, 0, 0], [40, 40, 40], [5, 5, 5])
PLAN_TOML = ('[[beam]]\ntype = "parallel"\nenergy_mev = 1.25\nposition_mm = [20.0, 20.0, -100.0]\n'
             'direction = [0.0, 0.0, 1.0]\nfield_mm = [30.0, 30.0]\n')


def _mesh():
    m = box_mesh([5, 5, 5], [35, 35, 35], (3, 3, 3), jitter=0.2, seed=2)
    return m.with_data(point_data={"density": np.full(m.n_points, 1.0)})


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    d = tmp_path_factory.mktemp("ompmc_cli")
    write_image(d / "ct.nrrd", Image(np.zeros(GRID.shape, dtype=np.int16), GRID))  # 0 HU
    write_mesh(d / "mesh.vtu", _mesh())
    (d / "plan.toml").write_text(PLAN_TOML)
    return d


def test_dose_on_the_ct_and_on_the_mesh_by_energy(inputs, tmp_path, monkeypatch):
    """ompmc runs on one OpenMP thread here (its thread count is numba's): with two, one voxel of
    512 once differed by 3.5 % between two same-seed runs under CI load (ompmc's scheduling)."""
    import numba

    monkeypatch.setattr(numba, "get_num_threads", lambda: 1)
    base = ["dose", "-q", "--ct", str(inputs / "ct.nrrd"), "--plan", str(inputs / "plan.toml"),
            "--histories", "2000", "--batches", "4", "--engine", "ompmc"]
    assert main([*base, "-o", str(tmp_path / "dose.nrrd")]) == 0
    record = json.loads((tmp_path / "dose.json").read_text())
    assert record["engine"] == "ompmc" and record["geometry"] == "voxel"
    voxel = read_image(tmp_path / "dose.nrrd")
    assert voxel.grid.same_as(GRID) and voxel.array.max() > 0
    assert main([*base, "--mesh", str(inputs / "mesh.vtu"), "-o", str(tmp_path / "m.vtu")]) == 0
    on_mesh = read_mesh(tmp_path / "m.vtu").cell_data["dose"]
    same = read_image(tmp_path / "m.nrrd")
    np.testing.assert_array_equal(same.array, voxel.array)  # same seed, same particles
    density = Image(HUCalibration.schneider2000().density(np.zeros(GRID.shape)), GRID)
    expected, _ = voxel_dose_onto_mesh(same, density, _mesh())
    np.testing.assert_allclose(on_mesh, expected, rtol=1e-5)  # float32 dose image
    assert json.loads((tmp_path / "m.json").read_text())["world"].startswith("mesh")


def test_dose4d_with_ompmc_accumulates_the_phases_energy(inputs, tmp_path):
    ref = _mesh()
    pts = np.stack([ref.points_mm, ref.points_mm + [0.0, 0.0, 2.0]])
    series = PhaseSeries(ref, pts, np.array([0.0, 50.0])).with_density(
        np.repeat(ref.point_data["density"][None], 2, axis=0))
    plan = Plan((PhotonSource("parallel", [20, 20, -100], [0, 0, 1], energies_mev=[1.25],
                              field_mm=[30, 30]),))
    ct = Image(np.zeros(GRID.shape, dtype=np.int16), GRID)
    run = run_dose4d(series, plan, TransportSettings(2000, 4, 3), ct_hu=ct,
                     voxel_engine=phase_engine(OmpmcOptions(electron_cutoff_mev=15.0)))
    assert [r.extra["engine"] for r in run.results] == ["ompmc", "ompmc"]
    assert run.results[0].energy_per_batch_mev.sum() != run.results[1].energy_per_batch_mev.sum()
    # each phase: its voxel dose put on its own (moved) mesh by energy
    for k, (r, v) in enumerate(zip(run.results, run.voxel.results, strict=True)):
        dose_k, _ = voxel_dose_onto_mesh(v.to_images()[0], run.voxel.density[k], series.mesh(k))
        np.testing.assert_allclose(r.dose_gy, dose_k, rtol=1e-12)
    # mesh masses kept (rigid shift): the accumulation is the mean of the phases' doses
    np.testing.assert_allclose(run.accumulated.dose_gy,
                               (run.results[0].dose_gy + run.results[1].dose_gy) / 2, rtol=1e-12)
    assert run.voxel.energy_mass_transfer.array.max() > 0


def test_cli_dose4d_with_ompmc(inputs, tmp_path):
    assert main(["deform", "-q", "--mesh", str(inputs / "mesh.vtu"), "--breathing",
                 "--n-phases", "2", "--amplitude-mm", "3", "-o", str(tmp_path / "phases")]) == 0
    assert main(["dose4d", "-q", "--phases", str(tmp_path / "phases"), "--plan",
                 str(inputs / "plan.toml"), "--histories", "1000", "--batches", "4",
                 "--like", str(inputs / "ct.nrrd"), "--engine", "ompmc",
                 "-o", str(tmp_path / "dose4d")]) == 0
    acc = read_mesh(tmp_path / "dose4d" / "accumulated.vtu")
    assert acc.cell_data["dose"].max() > 0
    record = json.loads((tmp_path / "dose4d" / "phase_000.0.json").read_text())
    assert record["engine"] == "ompmc" and record["geometry"] == "mesh"
    assert (tmp_path / "dose4d" / "voxel" / "accumulated_energy_mass_transfer.nrrd").exists()


@pytest.mark.parametrize(("extra", "message"), [
    (["--mesh", "MESH", "-o", "OUT/dose.vtu"], "give --ct"),
    (["--ct", "CT", "--dask", "local:1", "-o", "OUT/dose.nrrd"], "drop --dask"),
])
def test_refusals(inputs, tmp_path, capsys, extra, message):
    args = [a.replace("MESH", str(inputs / "mesh.vtu")).replace("CT", str(inputs / "ct.nrrd"))
            .replace("OUT", str(tmp_path)) for a in extra]
    code = main(["dose", "-q", "--plan", str(inputs / "plan.toml"), "--engine", "ompmc",
                 "--histories", "100", "--batches", "2", *args])
    err = capsys.readouterr().err
    assert code == 2 and message in err and len(err.strip().splitlines()) == 1
    assert not any(tmp_path.iterdir())
