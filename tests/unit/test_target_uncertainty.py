"""A run that stops at a target uncertainty: it stops when the region's batch statistics reach the
target, keeps the histories it ran bit for bit, and says so in its metadata."""

import argparse

import numba
import numpy as np
import pytest

from tetdose.cli._dose import relative_uncertainty
from tetdose.errors import PlanError
from tetdose.transport import PhotonSource, Plan, TransportSettings, World, simulate
from tetdose.transport.run.job import region_uncertainty

from helpers import density_image, grid_for


def _world_and_plan():
    grid = grid_for((-30, -30, 0), (30, 30, 60), (10.0, 10.0, 10.0))
    density = density_image(grid, lambda x, y, z: np.ones_like(x))
    c = grid.voxel_centers_mm()
    labels = density.with_array(((np.abs(c[:, 0]) < 10) & (np.abs(c[:, 1]) < 10)
                                 & (c[:, 2] < 30)).reshape(grid.shape).astype(np.int16))
    beam = PhotonSource("parallel", [0, 0, -10], [0, 0, 1], energies_mev=[1.25], field_mm=[20, 20])
    return World(density=density, labels=labels), Plan((beam,), regions={"core": 1})


def test_region_uncertainty_is_the_batch_standard_error_of_the_region_dose():
    rng = np.random.default_rng(4)
    rows = [(rng.random((3, 5)), None, None), (rng.random((2, 5)), None, None)]
    per_batch = np.array([10, 10, 11, 10, 10])
    cells = np.array([True, False, True, True, False])
    x = np.concatenate([r[0] for r in rows])[:, cells].sum(1) / per_batch
    expected = x.std(ddof=1) / np.sqrt(len(x)) / x.mean()
    assert region_uncertainty(rows, per_batch, cells) == pytest.approx(expected, rel=1e-12)
    assert region_uncertainty(rows[:1][:1], per_batch, np.zeros(5, bool)) == float("inf")


def test_run_stops_at_the_target_and_keeps_its_histories_bitwise():
    world, plan = _world_and_plan()
    full = simulate(world, plan, TransportSettings(20_000, 40, 3, physics="kerma"), progress=False)
    cells = np.concatenate([np.zeros(0, bool), world.labels.array.ravel() == 1])
    full_u = float(np.sqrt((full.dose_std_gy[cells] ** 2 * full.mass_g[cells] ** 2).sum())
                   / (full.dose_gy[cells] * full.mass_g[cells]).sum())
    target = 2.0 * full_u * np.sqrt(40 / 8)  # reachable after some 8–16 of the 40 batches
    st = TransportSettings(20_000, 40, 3, target_uncertainty=target, target_region="core", physics="kerma")
    early = simulate(world, plan, st, progress=False)
    info = early.extra["target"]
    assert info["reached"] and info["batches"] < 40 and info["achieved"] <= target
    assert early.n_batches == info["batches"] and early.n_histories == info["histories"]
    assert info["batches"] % (2 * numba.get_num_threads()) == 0 or info["batches"] == 40
    b = early.n_batches
    assert np.array_equal(early.energy_per_batch_mev, full.energy_per_batch_mev[:b])


def test_target_needs_a_structure_and_a_sane_value():
    world, plan = _world_and_plan()
    with pytest.raises(PlanError, match="target-region"):
        simulate(world, plan, TransportSettings(1000, 4, target_uncertainty=0.01, physics="kerma"),
                 progress=False)
    with pytest.raises(PlanError, match="relative standard error"):
        TransportSettings(1000, 4, target_uncertainty=1.0, physics="kerma")
    assert relative_uncertainty("1%") == pytest.approx(0.01)
    assert relative_uncertainty("0.02") == pytest.approx(0.02)
    with pytest.raises(argparse.ArgumentTypeError):
        relative_uncertainty("150%")
