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


def test_dose4d_runs_each_phase_to_the_target_and_its_voxel_body_as_long():
    """With a reference CT (voxel-only bodies have no structures) every phase's mesh run stops
    at the target in its structure; the voxel-only run of that phase gets the same histories."""
    from dataclasses import replace

    from tetdose.core.image import Image
    from tetdose.dose.dose4d import run_dose4d
    from tetdose.motion import BreathingModel, update_series

    from helpers import box_mesh

    ref = box_mesh([0, 0, 0], [40, 40, 40], (3, 3, 3))
    ref = replace(ref, region=np.ones(ref.n_tets, dtype=np.int32))
    series = update_series(BreathingModel(amplitude_mm=4.0).series(ref, 2),
                           np.full(ref.n_points, 0.9))[0]
    grid = grid_for([-10, -10, -10], [50, 50, 50], [10, 10, 10])
    ct = Image(np.full(grid.shape, -100, dtype=np.int16), grid)
    beam = PhotonSource("parallel", [20, 20, -60], [0, 0, 1], energies_mev=[1.25], field_mm=[30, 30])
    plan = Plan((beam,), regions={"core": 1})
    st = TransportSettings(40_000, 40, 5, physics="kerma", target_uncertainty=0.01,
                           target_region="core")
    out = run_dose4d(series, plan, st, ct_hu=ct)
    for r, v in zip(out.results, out.voxel.results, strict=True):
        t = r.extra["target"]
        assert t["reached"] and t["achieved"] <= 0.01 and t["batches"] < 40
        assert v.n_histories == r.n_histories and v.n_batches == r.n_batches


def test_the_terminal_says_what_was_reached(tmp_path, capsys):
    from dataclasses import replace

    from tetdose.cli import main
    from tetdose.cli._dose import target_line
    from tetdose.core.io import write_mesh

    from helpers import box_mesh

    mesh = box_mesh([-20, -20, 0], [20, 20, 40], (3, 3, 3))
    mesh = replace(mesh, region=np.ones(mesh.n_tets, dtype=np.int32)).with_data(
        point_data={"density": np.ones(mesh.n_points)})
    write_mesh(tmp_path / "m.vtu", mesh)
    (tmp_path / "plan.toml").write_text('[[beam]]\ntype = "parallel"\nenergy_mev = 1.25\n'
                                        'position_mm = [0.0, 0.0, -10.0]\nfield_mm = [40.0, 40.0]\n'
                                        '[regions]\ncore = 1\n')
    assert main(["dose", "--mesh", str(tmp_path / "m.vtu"), "--plan", str(tmp_path / "plan.toml"),
                 "--histories", "20000", "--batches", "40", "--physics", "kerma",
                 "--target-uncertainty", "2%", "--target-region", "core",
                 "-o", str(tmp_path / "d.vtu")]) == 0
    assert "target σ 2 % of the mean dose in core: reached (" in capsys.readouterr().out
    missed = {"uncertainty": 0.01, "region": None, "reached": False, "batches": 10,
              "histories": 1000, "achieved": 0.03}
    line = target_line([missed, {**missed, "reached": True, "achieved": 0.009}])
    assert "prescription structure: NOT reached in 1 of 2" in line and "3 %, 0.9 %" in line


def test_median_statistic_is_the_median_cell_sigma_and_stops_the_run():
    from tetdose.transport.run.job import median_uncertainty

    rng = np.random.default_rng(5)
    rows = [(rng.random((3, 6)) + 0.5, None, None), (rng.random((3, 6)) + 0.5, None, None)]
    per_batch = np.array([10, 10, 11, 10, 10, 12])
    cells = np.array([True, True, False, True, True, True])
    x = np.concatenate([r[0] for r in rows])[:, cells] / per_batch[:, None]
    rel = x.std(axis=0, ddof=1) / np.sqrt(6) / x.mean(axis=0)
    assert median_uncertainty(rows, per_batch, cells) == pytest.approx(np.median(rel), rel=1e-12)
    world, plan = _world_and_plan()
    st = TransportSettings(20_000, 40, 3, target_uncertainty=0.05, target_region="core",
                           target_statistic="median", physics="kerma")
    res = simulate(world, plan, st, progress=False)
    t = res.extra["target"]
    core = world.labels.array.ravel() == 1
    assert t["reached"] and t["statistic"] == "median" and res.n_batches < 40
    assert np.median(res.relative_uncertainty[core]) == pytest.approx(t["achieved"], rel=1e-9)
    with pytest.raises(PlanError, match="target_statistic"):
        TransportSettings(100, 4, target_statistic="max")


def test_ompmc_refuses_the_median_statistic():
    from tetdose.coupling.ompmc import _target_weights
    from tetdose.errors import OptionError

    _, plan = _world_and_plan()
    st = TransportSettings(100, 4, target_uncertainty=0.1, target_statistic="median")
    with pytest.raises(OptionError, match="target-statistic median"):
        _target_weights(None, None, None, plan, st)
