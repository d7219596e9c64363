"""tetdose.compare.comparison: the mesh-vs-voxel workflow behind `tetdose compare`."""

import json

import numpy as np
import pytest

from tetdose.compare.comparison import (
    compare_doses,
    half_inside,
    labels_on,
    recorded_dose_unit,
)
from tetdose.core.image import Image, ImageGrid
from tetdose.core.overlap import compute_overlap
from tetdose.core.transfer import mesh_dose_to_grid
from tetdose.errors import GeometryMismatchError, OptionError
from tetdose.plan.prescription import PER_PHOTON_UNIT

from helpers import box_mesh, grid_for


@pytest.fixture(scope="module")
def case():
    mesh = box_mesh((-10, -10, -10), (10, 10, 10), (3, 3, 3), jitter=0.1, seed=2)
    dose = 1.0 + 0.02 * mesh.centroids_mm[:, 2]  # a gentle gradient along z [Gy]
    grid = grid_for((-20, -20, -20), (20, 20, 20), (4.0, 4.0, 4.0))
    return mesh, dose, grid


def test_a_voxel_dose_equal_to_the_mesh_dose_passes_everywhere(case):
    mesh, dose, grid = case
    voxel = mesh_dose_to_grid(mesh, dose, grid)
    result = compare_doses(mesh, dose, voxel, gamma_max_points=None, unit="Gy per fraction")
    s = result.summary
    assert s["unit"] == "Gy per fraction" and s["mean_abs_difference_gy"] == 0.0
    assert all(g["pass_rate_percent"] == 100.0 for g in s["gamma"].values())
    assert s["region"]["voxels"] == int(half_inside(compute_overlap(mesh, grid)).sum()) > 0
    assert s["region"]["volume_cm3"] == pytest.approx(s["region"]["voxels"] * 64 / 1000)
    assert any("[Gy per fraction]" in f.caption for f in result.figures)


def test_a_dose_off_by_ten_percent_fails_three_percent_gamma(case):
    mesh, dose, grid = case
    voxel = mesh_dose_to_grid(mesh, 1.1 * dose, grid)
    result = compare_doses(mesh, dose, voxel, criteria=((3.0, 3.0, False),))
    s = result.summary
    assert s["gamma"]["3%/3mm global"]["pass_rate_percent"] < 50.0
    assert s["unit"] == PER_PHOTON_UNIT
    assert result.figures[0].caption.endswith("[Gy per source photon]")


def test_refusals(case):
    mesh, dose, grid = case
    far = ImageGrid((11.5, 11.5, 11.5), (4.0, 4.0, 4.0), np.eye(3), (3, 3, 3))  # corner only
    with pytest.raises(GeometryMismatchError, match="half inside the mesh"):
        compare_doses(mesh, dose, Image(np.ones(far.shape), far))
    with pytest.raises(OptionError, match="'voxel' or 'mesh'"):
        compare_doses(mesh, dose, mesh_dose_to_grid(mesh, dose, grid), reference="ct")


def test_labels_on_another_grid_take_the_voxel_holding_each_centre():
    fine = ImageGrid((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), np.eye(3), (4, 4, 4))
    lab = np.arange(64).reshape(4, 4, 4)
    coarse = ImageGrid((0.5, 0.5, 0.5), (2.0, 2.0, 2.0), np.eye(3), (3, 2, 2))
    got = labels_on(Image(lab, fine), coarse)
    # centres at 0.5, 2.5, 4.5 along x: index 0.5 → voxel 1 (face goes up), 2.5 → 3, 4.5 → off
    expected = np.zeros(coarse.shape, np.int64)
    for k in range(2):
        for j in range(2):
            for i, fi in ((0, 1), (1, 3)):
                expected[k, j, i] = lab[2 * k + 1, 2 * j + 1, fi]
    np.testing.assert_array_equal(got, expected)


def test_recorded_dose_unit_reads_the_run_record(tmp_path):
    (tmp_path / "dose.json").write_text(json.dumps({"units": {"dose": "Gy per fraction"}}))
    assert recorded_dose_unit(tmp_path / "dose.vtu") == "Gy per fraction"
    assert recorded_dose_unit(tmp_path / "other.vtu") == PER_PHOTON_UNIT
