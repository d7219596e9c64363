"""4D dose on a dask cluster: bitwise the local run (phases, voxels, accumulations) and the CLI."""

from __future__ import annotations

import json
import sys
from dataclasses import replace

import numpy as np
import pytest

from tetdose.cli import main
from tetdose.core.image import Image
from tetdose.core.io import read_mesh, write_mesh
from tetdose.dose.dose4d import run_dose4d
from tetdose.errors import PlanError
from tetdose.motion import BreathingModel, update_series
from tetdose.transport import PhotonSource, Plan, TransportSettings
from tetdose.transport.run.distributed import dask_client, simulate_distributed

from helpers import box_mesh, grid_for

distributed = pytest.importorskip("distributed", reason="dask.distributed is not installed "
                                  "(pip install 'tetdose[dask]')")

PLAN = Plan((PhotonSource("parallel", [20.0, 20.0, -60.0], [0, 0, 1], energies_mev=[1.25],
                          field_mm=[20.0, 20.0]),))
SETTINGS = TransportSettings(3000, 6, 11, estimator="analog", physics="kerma")
GRID = grid_for([0, 0, 0], [40, 40, 40], [5, 5, 5])
PLAN_TOML = ('[[beam]]\ntype = "parallel"\nenergy_mev = 1.25\nposition_mm = [20.0, 20.0, -60.0]\n'
             'direction = [0.0, 0.0, 1.0]\nfield_mm = [20.0, 20.0]\n')


@pytest.fixture(scope="module")
def client():
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster, \
            distributed.Client(cluster) as c:
        yield c


def breathing_series(n_phases: int = 3):
    """Water box with a density gradient, breathing 6 mm (mass-conserving phase densities)."""
    ref = box_mesh([0, 0, 0], [40, 40, 40], (4, 4, 4), jitter=0.15, seed=3)
    rho = 0.9 + 0.005 * ref.points_mm[:, 2]
    series = BreathingModel(amplitude_mm=6.0).series(ref, n_phases)
    return update_series(series, rho)[0]


def ct_hu() -> Image:
    return Image(np.full(GRID.shape, -200, dtype=np.int16), GRID)


def assert_same_result(a, b):
    np.testing.assert_array_equal(a.energy_per_batch_mev, b.energy_per_batch_mev)
    np.testing.assert_array_equal(a.ledger_per_batch_mev, b.ledger_per_batch_mev)
    np.testing.assert_array_equal(a.counts_per_batch, b.counts_per_batch)
    np.testing.assert_array_equal(a.dose_gy, b.dose_gy)
    np.testing.assert_array_equal(a.dose_std_gy, b.dose_std_gy)


@pytest.fixture(scope="module")
def local_run():
    return run_dose4d(breathing_series(), PLAN, SETTINGS, ct_hu=ct_hu())


@pytest.mark.parametrize("batches_per_task", [1, 4])
def test_dose4d_on_a_cluster_is_bitwise_the_local_run(client, local_run, batches_per_task):
    remote = run_dose4d(breathing_series(), PLAN, SETTINGS, ct_hu=ct_hu(), client=client,
                        batches_per_task=batches_per_task)
    for a, b in zip(remote.results, local_run.results, strict=True):
        assert_same_result(a, b)
        assert a.extra["task_s"] > 0  # worker time of this phase's batches
    for a, b in zip(remote.voxel.results, local_run.voxel.results, strict=True):
        assert_same_result(a, b)
    np.testing.assert_array_equal(remote.accumulated.dose_gy, local_run.accumulated.dose_gy)
    np.testing.assert_array_equal(remote.accumulated.dose_std_gy,
                                  local_run.accumulated.dose_std_gy)
    np.testing.assert_array_equal(remote.voxel.direct_mapping.array,
                                  local_run.voxel.direct_mapping.array)
    np.testing.assert_array_equal(remote.voxel.energy_mass_transfer.array,
                                  local_run.voxel.energy_mass_transfer.array)


def test_phases_use_their_own_streams_and_geometry(local_run):
    """Not vacuous: the phases' doses differ (moved anatomy, stream k), mesh and voxel alike."""
    mesh0, mesh1 = local_run.results[0], local_run.results[1]
    assert mesh0.dose_gy.max() > 0 and not np.array_equal(mesh0.dose_gy, mesh1.dose_gy)
    vox = local_run.voxel.results
    assert not np.array_equal(vox[0].dose_gy, vox[1].dose_gy)


def test_per_geometry_settings_select_the_stream(client):
    """simulate_distributed with one settings per geometry = local runs with those settings."""
    mesh = breathing_series(1).mesh(0)
    streams = [SETTINGS, TransportSettings(3000, 6, 11, estimator="analog", stream=4, physics="kerma")]
    from tetdose.transport import simulate

    remote = simulate_distributed(client, [mesh, mesh], PLAN, streams, progress=False)
    for res, st in zip(remote, streams, strict=True):
        assert_same_result(res, simulate(mesh, PLAN, st, progress=False))
    assert not np.array_equal(remote[0].dose_gy, remote[1].dose_gy)
    with pytest.raises(PlanError, match="one per geometry"):
        simulate_distributed(client, [mesh, mesh], PLAN, streams[:1])


@pytest.mark.parametrize("spec", ["local:0", "local:x", "local:-1"])
def test_bad_local_spec_raises(spec):
    with pytest.raises(PlanError, match="local:N"):
        with dask_client(spec):
            pass


def test_local_spec_starts_worker_processes_and_leaves_this_process_alone():
    """local:N: N worker processes (not this one), same dose; this process's numba is untouched.

    The same geometry three times (as symmetric breathing phases are), with its own stream each.
    """
    import os

    import numba

    from tetdose.transport import simulate

    mesh = breathing_series(1).mesh(0)
    streams = [replace(SETTINGS, stream=k) for k in range(3)]
    threads_before = numba.get_num_threads()
    with dask_client("local:2") as c:
        info = c.run(os.getpid)
        remote = simulate_distributed(c, [mesh] * 3, PLAN, streams, progress=False)
    assert len(info) == 2 and os.getpid() not in set(info.values())
    assert "NUMBA_NUM_THREADS" not in os.environ and numba.get_num_threads() == threads_before
    for res, st in zip(remote, streams, strict=True):
        assert_same_result(res, simulate(mesh, PLAN, st, progress=False))


def test_cli_dose_with_local_cluster_matches_plain_run(tmp_path):
    """`tetdose dose --dask local:2` (worker processes) writes the same dose as the local run."""
    mesh = breathing_series(1).mesh(0)
    write_mesh(tmp_path / "mesh.vtu", mesh)
    (tmp_path / "plan.toml").write_text(PLAN_TOML)
    common = ["dose", "--physics", "kerma", "-q", "--mesh", str(tmp_path / "mesh.vtu"), "--plan",
              str(tmp_path / "plan.toml"), "--histories", "2000", "--batches", "4"]
    assert main([*common, "-o", str(tmp_path / "local.vtu")]) == 0
    assert main([*common, "--dask", "local:2", "-o", str(tmp_path / "dask.vtu")]) == 0
    local, remote = read_mesh(tmp_path / "local.vtu"), read_mesh(tmp_path / "dask.vtu")
    assert local.cell_data["dose"].max() > 0
    np.testing.assert_array_equal(remote.cell_data["dose"], local.cell_data["dose"])
    np.testing.assert_array_equal(remote.cell_data["dose_std"], local.cell_data["dose_std"])
    assert json.loads((tmp_path / "dask.json").read_text())["dask"] == "local:2"


def test_cli_dose4d_with_dask_and_missing_dask(tmp_path, monkeypatch, capsys):
    series = breathing_series(2)
    series.write(tmp_path / "phases")
    (tmp_path / "plan.toml").write_text(PLAN_TOML)
    common = ["dose4d", "--physics", "kerma", "-q", "--phases", str(tmp_path / "phases"), "--plan",
              str(tmp_path / "plan.toml"), "--histories", "2000", "--batches", "4"]
    assert main([*common, "-o", str(tmp_path / "local")]) == 0
    assert main([*common, "--dask", "local:1", "-o", str(tmp_path / "dask")]) == 0
    for name in ("phase_000.0.vtu", "phase_050.0.vtu", "accumulated.vtu"):
        a, b = read_mesh(tmp_path / "local" / name), read_mesh(tmp_path / "dask" / name)
        np.testing.assert_array_equal(a.cell_data["dose"], b.cell_data["dose"])
    monkeypatch.setitem(sys.modules, "distributed", None)  # import now raises ImportError
    assert main([*common, "--dask", "local:1", "-o", str(tmp_path / "none")]) == 2
    assert "tetdose[dask]" in capsys.readouterr().err
    assert not (tmp_path / "none").exists()
