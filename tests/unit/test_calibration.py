"""HU ↔ density calibration, including the inverse rule on Schneider's non-monotonic table."""

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
