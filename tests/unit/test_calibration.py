"""HU ↔ density calibration, including the inverse rule on Schneider's non-monotonic table."""

import warnings

import numpy as np
import pytest

from tetdose.core.calibration import SCHNEIDER_2000, HUCalibration
from tetdose.errors import CalibrationError

from conftest import SHARED


def test_nodes_are_reproduced_and_ends_are_held():
    cal = HUCalibration.schneider2000()
    nodes = np.array(SCHNEIDER_2000)
    np.testing.assert_allclose(cal(nodes[:, 0]), nodes[:, 1])
    assert cal(-1200) == pytest.approx(0.00121)
    assert cal(5000) == pytest.approx(2.8)
    assert cal(0.0) == pytest.approx(0.930486 + (1.03 - 0.930486) * 97 / 111)


@pytest.mark.skipif(not (SHARED / "reference/schneider").exists(), reason="../shared absent")
def test_default_table_matches_the_shared_schneider_file():
    rows = np.loadtxt(SHARED / "reference/schneider/Schneider2000DensitiesTable.txt", comments="#")
    np.testing.assert_allclose(np.array(SCHNEIDER_2000), rows)


def test_inverse_is_the_lowest_hu_reaching_the_density():
    cal = HUCalibration.schneider2000()
    rho = np.linspace(0.00121, 2.8, 5001)
    np.testing.assert_allclose(cal(cal.hu_of(rho)), rho, atol=1e-12)
    # Brute force: lowest HU on a fine grid whose density reaches rho.
    hu = np.arange(-1000, 3000.0001, 0.01)
    f = np.maximum.accumulate(cal(hu))
    for r in (0.5, 1.0, 1.08, 1.1, 1.119, 1.5):
        assert cal.hu_of(r) == pytest.approx(hu[np.searchsorted(f, r)], abs=0.02)
    # The ambiguous band 101…~175 HU maps back onto the soft-tissue branch.
    assert cal.hu_of(cal(150.0)) < 100.0
    np.testing.assert_allclose(cal.hu_of(cal(np.array([-500.0, 0.0, 50.0, 800.0]))),
                               [-500.0, 0.0, 50.0, 800.0], atol=1e-9)


def test_csv_round_trip_and_errors(tmp_path):
    good = tmp_path / "cal.csv"
    good.write_text("hu,density\n-1000,0.001\n0,1.0\n2000,2.0\n")
    cal = HUCalibration.from_csv(good)
    assert cal(1000) == pytest.approx(1.5)
    bad = tmp_path / "bad.csv"
    bad.write_text("-1000,0.001\n0,1.0\n0,1.1\n")
    with pytest.raises(CalibrationError, match="strictly increasing"):
        HUCalibration.from_csv(bad)
    with pytest.raises(CalibrationError, match="cannot read"):
        HUCalibration.from_csv(tmp_path / "missing.csv")


def test_hu_beyond_the_table_are_counted_and_metal_warned():
    """Issue 27: a 20 000 HU metal insert silently became 2.8 g/cm³ bone."""
    cal = HUCalibration.schneider2000()
    hu = np.array([-3024.0, -1024.0, 0.0, 2999.0, 20000.0, 8000.0])
    report = cal.range_report(hu)
    assert (report.n_below, report.n_above) == (2, 2)
    assert (report.lowest_hu, report.highest_hu) == (-3024.0, 20000.0)
    assert report.density_above_g_cm3 == 2.8 and report.table_hu == (-1000.0, 3000.0)
    with pytest.warns(UserWarning, match=r"the CT x: 2 voxels lie above .*3000 HU, up to 20000 "
                      r"HU\) and became 2.8 g/cm³.*give --calibration a CSV extending"):
        rho, _ = cal.density_checked(hu, "the CT x")
    np.testing.assert_array_equal(rho, cal.density(hu))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # air padding below the table: counted, not warned
        assert cal.density_checked(hu[:4])[1].n_below == 2
    extended = HUCalibration(np.r_[cal.hu, 20000.0], np.r_[cal.density_g_cm3, 4.5])
    assert extended.range_report(hu).n_above == 0
    assert extended.density(20000.0) == pytest.approx(4.5)


def test_map_warns_about_metal_in_the_ct():
    from tetdose.core.image import Image, ImageGrid
    from tetdose.mapping import map_density

    from helpers import box_mesh

    grid = ImageGrid([0.5, 0.5, 0.5], [1.0, 1.0, 1.0], np.eye(3), (4, 4, 4))
    ct = np.zeros(grid.shape, dtype=np.int16)
    ct[1, 1, 1] = 20000
    with pytest.warns(UserWarning, match="1 voxels lie above the calibration's last node"):
        map_density(box_mesh([0, 0, 0], [4, 4, 4], (2, 2, 2)), Image(ct, grid))


def test_cli_dose_records_and_prints_hu_beyond_the_table(tmp_path, capsys, monkeypatch):
    """Both the warning line and the record in dose.json (voxel engine, kerma: fast)."""
    import json
    import sys

    # pytest records warnings itself; print them as Python does outside pytest
    monkeypatch.setattr(warnings, "_showwarnmsg_impl",
                        lambda msg: sys.stderr.write(warnings._formatwarnmsg(msg)))
    monkeypatch.setattr(warnings, "filters", [("always", None, Warning, None, 0)])

    from tetdose.cli import main
    from tetdose.core.image import Image, ImageGrid
    from tetdose.core.io import write_image

    grid = ImageGrid([1.0, 1.0, 1.0], [2.0, 2.0, 2.0], np.eye(3), (6, 6, 6))
    ct = np.zeros(grid.shape, dtype=np.int16) - 1024  # air padding: below the table
    ct[1:5, 1:5, 1:5] = 0
    ct[2, 2, 2] = 20000  # a metal insert
    write_image(tmp_path / "ct.nrrd", Image(ct, grid))
    (tmp_path / "plan.toml").write_text('[[beam]]\ntype = "pencil"\nenergy_mev = 1.0\n'
                                        'position_mm = [6.0, 6.0, -50.0]\ndirection = [0, 0, 1]\n')
    assert main(["dose", "-q", "--ct", str(tmp_path / "ct.nrrd"), "--plan",
                 str(tmp_path / "plan.toml"), "--physics", "kerma", "--histories", "300",
                 "-o", str(tmp_path / "dose.nrrd")]) == 0
    err = capsys.readouterr().err
    assert "tetdose dose: warning: the CT" in err and "1 voxels lie above the calibration" in err
    record = json.loads((tmp_path / "dose.json").read_text())["hu_beyond_calibration"]
    assert (record["n_above"], record["n_below"], record["highest_hu"]) == (1, 152, 20000.0)


def test_a_table_in_kg_per_m3_is_refused(tmp_path):
    (tmp_path / "cal.csv").write_text("HU,density\n-1000,1.2\n0,1030\n")
    with pytest.raises(CalibrationError, match="densities reach 1030, denser than any material"):
        HUCalibration.from_csv(tmp_path / "cal.csv")
