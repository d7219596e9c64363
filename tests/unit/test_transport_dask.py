"""dask.distributed transport: bitwise the local result for the same seed (batches and phases)."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from tetdose.core.image import Image
from tetdose.errors import PlanError, TetdoseError
from tetdose.transport import PhotonSource, Plan, TransportSettings, World, simulate
from tetdose.transport.run.distributed import _distributed, simulate_distributed

from helpers import box_mesh, grid_for

PLAN = Plan((PhotonSource("parallel", [0.0, 0.0, -20.0], [0, 0, 1], energies_mev=[1.25],
                          field_mm=[20.0, 20.0]),))
SETTINGS = TransportSettings(3000, 6, 17, estimator="analog", physics="kerma")


@pytest.fixture(scope="module")
def client():
    distributed = pytest.importorskip("distributed", reason="dask.distributed is not installed "
                                      "(pip install 'tetdose[dask]')")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster, \
            distributed.Client(cluster) as c:
        yield c


def _phases():
    mesh = box_mesh((-20, -20, 0), (20, 20, 40), (3, 3, 4), jitter=0.2, seed=1)
    base = mesh.with_data(point_data={"density": 1.0 + 0.002 * mesh.points_mm[:, 2]})
    moved = base.moved(base.points_mm * np.array([1.0, 1.0, 1.1]))
    return [base, moved]


def _same(a, b):
    np.testing.assert_array_equal(a.energy_per_batch_mev, b.energy_per_batch_mev)
    np.testing.assert_array_equal(a.ledger_per_batch_mev, b.ledger_per_batch_mev)
    np.testing.assert_array_equal(a.counts_per_batch, b.counts_per_batch)


def test_phases_on_a_cluster_match_local_runs_bitwise(client):
    phases = _phases()
    remote = simulate_distributed(client, phases, PLAN, SETTINGS, batches_per_task=4,
                                  progress=False)
    assert len(remote) == 2
    for geom, res in zip(phases, remote, strict=True):
        local = simulate(geom, PLAN, SETTINGS, progress=False)
        assert local.energy_per_batch_mev.sum() > 0
        _same(res, local)
    # the phases differ (the moved mesh is longer), so the comparison is not vacuous
    assert not np.array_equal(remote[0].energy_per_batch_mev, remote[1].energy_per_batch_mev)


def test_voxel_geometry_on_a_cluster_matches_local(client):
    grid = grid_for((-20, -20, 0), (20, 20, 40), (5.0, 5.0, 5.0))
    image = Image(np.ones(grid.shape), grid)
    _same(simulate_distributed(client, image, PLAN, SETTINGS, progress=False),
          simulate(image, PLAN, SETTINGS, progress=False))


def test_hybrid_world_on_a_cluster_matches_local(client):
    """A mesh inside a CT (the hybrid world) gives the same bits on the cluster."""
    grid = grid_for((-30, -30, -10), (30, 30, 50), (5.0, 5.0, 5.0))
    image = Image(np.full(grid.shape, 0.9), grid)
    world = World(mesh=_phases()[0], density=image)
    remote = simulate_distributed(client, world, PLAN, SETTINGS, progress=False)
    local = simulate(world, PLAN, SETTINGS, progress=False)
    assert local.geometry == "hybrid" and local.record()["mesh_voxel_switches"] > 0
    _same(remote, local)


def test_bad_arguments_raise(client):
    with pytest.raises(PlanError, match="Client"):
        simulate_distributed(object(), _phases()[0], PLAN, SETTINGS)
    with pytest.raises(PlanError, match="batches_per_task"):
        simulate_distributed(client, _phases()[0], PLAN, SETTINGS, batches_per_task=0)


def test_missing_dask_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "distributed", None)  # import now raises ImportError
    with pytest.raises(TetdoseError, match=r"tetdose\[dask\]"):
        _distributed()
