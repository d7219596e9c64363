"""`compare` says which matter each DVH covers: a mesh whose region differs from its voxel region.

A box mesh [2, 32.1] mm on 4 mm voxels (edges at 2, 6, …, 34): the last voxel of each axis is
52.5 % inside, so the compared voxels ("at least half inside": 7³ whole ones and the 3 · 7² of
the last layers that are partial along one axis only) reach 34 mm while the tetrahedra stop at
32.1 mm. The dose rises linearly along x, the same field on tets (at their centroids) and voxels
(at their centres). Expected values, independent of the code: tet volume 30.1³ mm³; the voxel
region from the product of the per-axis overlap lengths; the volume-weighted mean of a linear
field over the tets is its value at the box centre, over the voxels the mean over their centres.
"""

import json

import numpy as np
import pytest

from tetdose.compare.comparison import compare_doses
from tetdose.core.image import Image, ImageGrid
from tetdose.core.io import write_image, write_mesh

from helpers import box_mesh

LO, HI, SPACING = 2.0, 32.1, 4.0
SLOPE = 0.05  # Gy per mm along x


def _dose_at(x_mm):
    return 1.0 + SLOPE * x_mm


def _expected_region(grid):
    """Voxels ≥ half inside [LO, HI]³: coverage = Π_axis overlap length / spacing."""
    c = grid.voxel_centers_mm()
    part = np.clip(np.minimum(c + SPACING / 2, HI) - np.maximum(c - SPACING / 2, LO), 0, None)
    return (np.prod(part / SPACING, axis=1) >= 0.5).reshape(grid.shape), c[:, 0]


@pytest.fixture(scope="module")
def case():
    mesh = box_mesh((LO,) * 3, (HI,) * 3, (3, 3, 3))
    rho = np.full(mesh.n_points, 1.2)  # g/cm³
    mesh = mesh.with_data(point_data={"density": rho})
    dose = _dose_at(mesh.centroids_mm[:, 0])
    grid = ImageGrid(np.zeros(3), np.full(3, SPACING), np.eye(3), (10, 10, 10))
    x = grid.voxel_centers_mm()[:, 0].reshape(grid.shape)
    voxel = Image(_dose_at(x), grid)
    return mesh, dose, voxel


def test_regions_volumes_masses_and_both_means(case):
    mesh, dose, voxel = case
    density = Image(np.full(voxel.grid.shape, 1.2), voxel.grid)
    s = compare_doses(mesh, dose, voxel, gamma_max_points=2000, density=density).summary
    row = s["dvh"]["mesh"]
    tets, voxels = row["mesh"], row["voxel"]
    region, x = _expected_region(voxel.grid)
    assert region.sum() == 7**3 + 3 * 7**2
    v_tets = (HI - LO) ** 3 / 1000.0
    v_voxels = region.sum() * SPACING**3 / 1000.0
    assert tets["volume_cm3"] == pytest.approx(v_tets, rel=1e-12)
    assert tets["mass_g"] == pytest.approx(1.2 * v_tets, rel=1e-12)
    assert voxels["volume_cm3"] == pytest.approx(v_voxels, rel=1e-12)
    assert voxels["mass_g"] == pytest.approx(1.2 * v_voxels, rel=1e-12)
    assert tets["Dmean"] == pytest.approx(_dose_at((LO + HI) / 2), rel=1e-12)
    assert voxels["Dmean"] == pytest.approx(_dose_at(x[region.ravel()].mean()), rel=1e-12)
    # uniform density: the mass-weighted means equal the volume-weighted ones
    assert tets["Dmean_mass_weighted"] == pytest.approx(tets["Dmean"], rel=1e-12)
    assert voxels["Dmean_mass_weighted"] == pytest.approx(voxels["Dmean"], rel=1e-12)
    # the same voxels: most of the difference is the regions'
    total = 100 * (tets["Dmean"] / voxels["Dmean"] - 1)
    same = row["same_voxels"]
    on_same = 100 * (same["mesh_Dmean"] / same["voxel_Dmean"] - 1)
    assert total == pytest.approx(100 * (_dose_at(17.05) / _dose_at(8624 / 490) - 1), abs=1e-9)
    assert abs(on_same) < abs(total) / 2
    note = row["note"]
    assert "different matter" in note and f"{1.2 * v_tets:.4g} g" in note
    assert f"{1.2 * v_voxels:.4g} g" in note and f"{total:+.1f} %" in note
    assert "from the regions" in note


def test_without_a_ct_the_voxel_masses_come_from_the_mesh(case):
    mesh, dose, voxel = case
    row = compare_doses(mesh, dose, voxel, gamma_max_points=2000).summary["dvh"]["mesh"]
    # every compared voxel is at least half inside: its density is the mesh's, 1.2 g/cm³
    assert row["voxel"]["mass_g"] == pytest.approx(1.2 * 490 * SPACING**3 / 1000, rel=1e-9)
    assert "estimated from the mesh" in row["mass_source"]


def test_no_note_when_the_regions_agree():
    mesh = box_mesh((2.0,) * 3, (34.0,) * 3, (2, 2, 2)).with_data(
        point_data={"density": np.ones(27)})
    grid = ImageGrid(np.zeros(3), np.full(3, SPACING), np.eye(3), (10, 10, 10))
    voxel = Image(np.ones(grid.shape), grid)
    row = compare_doses(mesh, np.ones(mesh.n_tets), voxel,
                        gamma_max_points=2000).summary["dvh"]["mesh"]
    assert row["mesh"]["volume_cm3"] == pytest.approx(row["voxel"]["volume_cm3"], rel=1e-12)
    assert "note" not in row


def test_cli_prints_and_writes_the_regions(case, tmp_path, capsys):
    from tetdose.cli import main

    mesh, dose, voxel = case
    write_mesh(tmp_path / "dose.vtu", mesh.with_data(cell_data={"dose": dose}))
    write_image(tmp_path / "vdose.nrrd", voxel)
    ct = Image(np.zeros(voxel.grid.shape, np.int16), voxel.grid)  # water: 0 HU
    write_image(tmp_path / "ct.nrrd", ct)
    (tmp_path / "cal.csv").write_text("HU,density\n-1000,0.0\n0,1.2\n3000,3.0\n")
    assert main(["compare", "-q", "--mesh-dose", str(tmp_path / "dose.vtu"), "--voxel-dose",
                 str(tmp_path / "vdose.nrrd"), "--ct", str(tmp_path / "ct.nrrd"),
                 "--calibration", str(tmp_path / "cal.csv"), "--gamma-max-points", "2000",
                 "-o", str(tmp_path / "cmp")]) == 0
    out = capsys.readouterr().out
    assert "DVH mesh: tets 27.27 cm³, 32.73 g" in out and "voxels 31.36 cm³, 37.63 g" in out
    assert "from the regions" in out
    row = json.loads((tmp_path / "cmp" / "summary.json").read_text())["dvh"]["mesh"]
    assert "--ct" in row["mass_source"] and row["voxel"]["mass_g"] == pytest.approx(37.632)
    assert "note" in row
    assert "different matter" in (tmp_path / "cmp" / "report.html").read_text()
