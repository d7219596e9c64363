"""CT voxels → compositions: Schneider's HU bins (default) against the published table, the label
image they make, and `tetdose dose --ct` with each rule; dose to water recorded in the outputs."""

import json
from pathlib import Path

import numpy as np
import pydicom
import pytest

from tetdose.cli import main
from tetdose.core.calibration import HUCalibration
from tetdose.core.composition import Z_OF
from tetdose.core.ct_materials import (
    FIRST_LABEL,
    schneider_bin,
    schneider_labels,
    schneider_materials,
)
from tetdose.core.image import Image, ImageGrid
from tetdose.core.io import write_image
from tetdose.errors import OptionError

TABLE = (Path(__file__).resolve().parents[2] / ".." / "shared" / "reference" / "schneider"
         / "Schneider2000MaterialsTable.txt")
CAL = HUCalibration.schneider2000()


def test_bins_match_the_published_table():
    if not TABLE.exists():
        pytest.skip(f"Schneider reference table not found at {TABLE} (../shared beside the checkout)")
    symbols = "H C N O Na Mg P S Cl Ar K Ca Ti Cu Zn Ag Sn".split()
    rows = [line.split() for line in TABLE.read_text().splitlines()
            if line.strip() and line.strip()[0] in "-0123456789"]
    mats = schneider_materials(CAL)
    assert len(mats) == 24 and len(rows) == 27  # GATE's amalgam and metal rows left out
    for m, row in zip(mats, rows, strict=False):
        assert m.name == f"schneider_{row[18].lower()}"
        want = {Z_OF[s]: float(v) / 100 for s, v in zip(symbols, row[1:18], strict=True)
                if float(v) > 0}
        assert dict(m.mass_fractions) == pytest.approx(want)
        assert schneider_bin(np.array([float(row[0])]))[0] == mats.index(m)


def test_bin_edges_and_nominal_densities():
    hu = np.array([-3000.0, -951.0, -950.0, -121.0, -120.0, 19.0, 79.0, 120.0, 1499.0, 4000.0])
    names = [schneider_materials(CAL)[k].name for k in schneider_bin(hu)]
    assert names == ["schneider_air", "schneider_air", "schneider_lung", "schneider_lung",
                     "schneider_at_ag_si1", "schneider_softtissus", "schneider_softtissus",
                     "schneider_marrow_bone01", "schneider_marrow_bone14",
                     "schneider_marrow_bone15"]
    mats = {m.name: m for m in schneider_materials(CAL)}
    assert mats["schneider_lung"].density_g_cm3 == pytest.approx(float(CAL.density(-535.0)))
    calcium = [dict(m.mass_fractions).get(20, 0.0) for m in mats.values()]
    assert np.all(np.diff(calcium[9:]) > 0)  # marrow → bone: more calcium with HU


def _ct() -> Image:
    grid = ImageGrid([-9.0, -9.0, 1.0], [6.0, 6.0, 2.0], np.eye(3), (4, 4, 30))
    depth = np.arange(30)
    hu = np.select([depth < 8, depth < 16, depth < 22], [40.0, -700.0, 1000.0], 40.0)
    return Image((hu[:, None, None] * np.ones(grid.shape)).astype(np.int16), grid)


def test_labels_keep_claimed_regions_and_bin_the_rest():
    ct = _ct()
    labels = Image(np.where(np.arange(30) < 4, 1, 0)[:, None, None] * np.ones(ct.grid.shape,
                                                                                 np.int16), ct.grid)
    lab, names, comps = schneider_labels(ct, CAL, labels, claimed={1})
    arr = np.asarray(lab.array)
    assert np.all(arr[:4] == 1)
    assert set(names.values()) == {"schneider_softtissus", "schneider_lung",
                                   "schneider_marrow_bone10"} == set(comps)
    assert names[int(arr[10, 0, 0])] == "schneider_lung"
    assert names[int(arr[18, 0, 0])] == "schneider_marrow_bone10"
    with pytest.raises(OptionError, match="reserved for Schneider"):
        schneider_labels(ct, CAL, labels.with_array(labels.array * 0 + FIRST_LABEL), claimed={1})


PLAN = """
[[beam]]
type = "parallel"
energy_mev = 2.0
position_mm = [0.0, 0.0, -10.0]
direction = [0.0, 0.0, 1.0]
field_mm = [12.0, 12.0]
"""


@pytest.fixture(scope="module")
def ct_dir(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("ctm")
    write_image(d / "ct.nrrd", _ct())
    (d / "plan.toml").write_text(PLAN)
    return d


@pytest.mark.parametrize("rule", ["schneider", "density-classes"])
def test_dose_records_the_ct_rule_and_its_compositions(ct_dir, tmp_path, rule):
    out = tmp_path / "dose.nrrd"
    assert main(["dose", "-q", "--ct", str(ct_dir / "ct.nrrd"), "--plan", str(ct_dir / "plan.toml"),
                 "--histories", "200", "--batches", "2", "--electron-cutoff-mev", "0.5", "--ct-materials",
                 rule, "-o", str(out)]) == 0
    rec = json.loads((tmp_path / "dose.json").read_text())
    assert rec["ct_materials"]["rule"] == rule
    assert rec["dose_to"] == "medium"
    if rule == "schneider":
        assert rec["ct_materials"]["voxels"]["schneider_lung"] == 8 * 16
        assert {"schneider_lung", "schneider_marrow_bone10"} <= set(rec["compositions"])
        assert rec["compositions"]["schneider_lung"]["composition"]["P"] == pytest.approx(0.002)
    else:
        assert {"lung", "cortical_bone", "soft_tissue"} <= set(rec["materials"])


def test_dose_to_water_is_recorded_in_json_and_rt_dose(ct_dir, tmp_path, capsys):
    out = tmp_path / "dose.nrrd"
    assert main(["dose", "-q", "--ct", str(ct_dir / "ct.nrrd"), "--plan", str(ct_dir / "plan.toml"),
                 "--histories", "200", "--batches", "2", "--electron-cutoff-mev", "0.5",
                 "--dose-to", "water", "-o", str(out)]) == 0
    rec = json.loads((tmp_path / "dose.json").read_text())
    assert rec["dose_to"] == "water"
    assert rec["dose_to_water"]["s_w_m"]["schneider_marrow_bone10"] > 1.05
    rt = tmp_path / "rt.dcm"
    with pytest.warns(UserWarning, match="Frame of Reference"):
        assert main(["export-dose", "-q", "--dose", str(out), "--like", str(ct_dir / "ct.nrrd"),
                     "-o", str(rt)]) == 0
    assert pydicom.dcmread(rt).DoseComment.startswith("dose to water")
    assert main(["export-dose", "-q", "--dose", str(out), "--like", str(ct_dir / "ct.nrrd"),
                 "--dose-to", "medium", "-o", str(tmp_path / "rt2.dcm")]) == 2
    assert "is dose to water, not to medium" in capsys.readouterr().err
