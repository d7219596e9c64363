"""`tetdose map | voxelize | evaluate` end to end in a temporary folder, asserting on outputs."""

import json

import numpy as np
import pytest

from tetdose.cli import main
from tetdose.core.calibration import HUCalibration
from tetdose.core.io import read_image, read_mesh, write_image, write_mesh

from helpers import box_mesh, density_image, grid_for

CAL = HUCalibration.schneider2000()


@pytest.fixture
def case(tmp_path):
    grid = grid_for([0, 0, 0], [24, 20, 16], [1.0, 1.0, 2.0])
    rho = density_image(grid, lambda x, y, z: np.where(x < 12, 0.26, 1.05) + 0.002 * y)
    ct = rho.with_array(np.round(CAL.hu_of(rho.array)).astype(np.int16))
    write_image(tmp_path / "ct.nrrd", ct)
    write_mesh(tmp_path / "mesh.vtu", box_mesh([3, 3, 2], [21, 17, 14], (6, 5, 4), jitter=0.2))
    return tmp_path, ct


def test_map_voxelize_evaluate(case, capsys):
    d, ct = case
    assert main(["map", "-q", "--ct", str(d / "ct.nrrd"), "--mesh", str(d / "mesh.vtu"),
                 "-o", str(d / "mapped.vtu")]) == 0
    mapped = read_mesh(d / "mapped.vtu")
    rho = mapped.point_data["density"]
    assert 0.2 < rho.min() and rho.max() < 1.15
    assert mapped.cell_data["mass_g"].sum() == pytest.approx(mapped.cell_data["ct_mass_g"].sum(),
                                                             rel=1e-9)
    assert main(["voxelize", "-q", "--mesh", str(d / "mapped.vtu"), "--like", str(d / "ct.nrrd"),
                 "--hu", "--background", "ct", "-o", str(d / "vct.nrrd")]) == 0
    vct = read_image(d / "vct.nrrd")
    assert vct.grid.same_as(ct.grid) and vct.array.dtype == np.int16
    outside = CAL(vct.array) == CAL(ct.array)  # background = CT outside the mesh
    assert outside.mean() > 0.3
    assert main(["evaluate", "-q", "--ct", str(d / "ct.nrrd"), "--mesh", str(d / "mapped.vtu"),
                 "-o", str(d / "report")]) == 0
    metrics = json.loads((d / "report" / "metrics.json").read_text())
    assert metrics["mass_error_in_mesh_pct"] < 1e-7
    rel = read_image(d / "report" / "relative_error.nrrd").array
    roi = rel > 0
    assert metrics["rmde_pct"] == pytest.approx(rel[roi].mean(), rel=1e-3)  # outputs agree
    assert 0 < metrics["rmde_pct"] < 30
    for name in ("reconstruction.nrrd", "error.nrrd", "relative_error.nrrd", "slices.png"):
        assert (d / "report" / name).stat().st_size > 0
    assert "RMDE" in capsys.readouterr().out


def test_bad_input_gives_exit_2_and_no_output(case, capsys):
    d, _ = case
    out = d / "never.vtu"
    far = box_mesh([500, 500, 500], [510, 510, 510], (1, 1, 1))
    write_mesh(d / "far.vtu", far)
    code = main(["map", "-q", "--ct", str(d / "ct.nrrd"), "--mesh", str(d / "far.vtu"),
                 "-o", str(out)])
    assert code == 2 and not out.exists()
    assert "wholly outside" in capsys.readouterr().err
    assert main(["map", "-q", "--ct", str(d / "missing.nrrd"), "--mesh", str(d / "mesh.vtu"),
                 "-o", str(out)]) == 2
    assert not out.exists()


def test_partly_outside_warns_with_fraction(case):
    d, _ = case
    write_mesh(d / "half.vtu", box_mesh([12, 3, 2], [36, 17, 14], (4, 2, 2)))
    with pytest.warns(UserWarning, match="50 % of the mesh volume lies outside"):
        main(["map", "-q", "--ct", str(d / "ct.nrrd"), "--mesh", str(d / "half.vtu"),
              "-o", str(d / "half_mapped.vtu")])
