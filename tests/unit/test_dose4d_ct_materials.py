"""dose4d's bodies get Schneider's HU → composition bins by default (as ``dose --ct``), from the
phase CTs (--ct4d) or the reference CT and the calibration's inverse (--like), or the five
density classes; the rule and the voxels of each bin are recorded in summary.json."""

import json
from pathlib import Path

import numpy as np
import pytest
from test_ct_materials import PLAN  # the same 12 mm 2 MeV beam along z

from tetdose.cli import main
from tetdose.core.calibration import HUCalibration
from tetdose.core.ct_materials import body_hu, schneider_bin, schneider_materials
from tetdose.core.image import Image, ImageGrid
from tetdose.core.io import write_image
from tetdose.dose.dose4d import run_dose4d
from tetdose.errors import OptionError
from tetdose.motion.phases import PhaseSeries
from tetdose.transport import Plan, TransportSettings

from helpers import box_mesh

CAL = HUCalibration.schneider2000()
#: Slabs along z (2 mm slices): soft tissue, lung, bone, soft tissue; the mesh sits in the last.
SLABS = ((8, 40.0), (16, -700.0), (22, 1000.0), (30, 40.0))


def _ct() -> Image:
    grid = ImageGrid([-9.0, -9.0, 1.0], [6.0, 6.0, 2.0], np.eye(3), (4, 4, 30))
    depth = np.arange(30)
    hu = np.select([depth < end for end, _ in SLABS], [h for _, h in SLABS])
    return Image((hu[:, None, None] * np.ones(grid.shape)).astype(np.int16), grid)


@pytest.fixture(scope="module")
def d(tmp_path_factory) -> Path:
    """The CT, two phases of a water box in its last slab (moved 1 mm), the plan."""
    d = tmp_path_factory.mktemp("d4ctm")
    write_image(d / "ct.nrrd", _ct())
    mesh = box_mesh([-6.0, -6.0, 46.0], [6.0, 6.0, 56.0], (2, 2, 2))
    ones = np.ones(mesh.n_points)
    PhaseSeries(mesh.with_data(point_data={"density": ones}),
                np.stack([mesh.points_mm, mesh.points_mm + [0.0, 0.0, 1.0]]),
                density_g_cm3=np.stack([ones, ones])).write(d / "phases")
    (d / "plan.toml").write_text(PLAN)
    return d


def test_body_hu_keeps_the_reference_hu_and_inverts_the_rest():
    ct = _ct()
    rho = CAL.density(np.asarray(ct.array, np.float64))
    rho[:2] = 0.5  # a body voxel that changed (e.g. entered by the moving mesh)
    hu = np.asarray(body_hu(Image(rho, ct.grid), CAL, ct).array)
    np.testing.assert_array_equal(hu[2:], np.asarray(ct.array)[2:])
    np.testing.assert_allclose(CAL.density(hu[:2]), 0.5)
    # around 100 HU Schneider's curve turns back: the reference CT's own HU keep marrow there,
    # the inverse alone (no reference CT) takes the lower, soft-tissue branch
    marrow = Image(np.full((1, 1, 1), 110.0), ImageGrid([0, 0, 0], [1, 1, 1], np.eye(3), (1, 1, 1)))
    dense = marrow.with_array(CAL.density(marrow.array))
    names = [m.name for m in schneider_materials(CAL)]
    assert names[schneider_bin(body_hu(dense, CAL, marrow).array)[0, 0, 0]] == \
        "schneider_connectivetissue"
    assert names[schneider_bin(body_hu(dense, CAL).array)[0, 0, 0]] == "schneider_softtissus"


@pytest.mark.parametrize("rule", ["schneider", "density-classes"])
def test_dose4d_like_records_the_rule_and_the_bins_of_each_phase(d, tmp_path, rule):
    out = tmp_path / "d4"
    assert main(["dose4d", "-q", "--physics", "kerma", "--phases", str(d / "phases"), "--plan",
                 str(d / "plan.toml"), "--like", str(d / "ct.nrrd"), "--histories", "200",
                 "--batches", "2", "--ct-materials", rule, "-o", str(out)]) == 0
    rec = json.loads((out / "summary.json").read_text())["ct_materials"]
    assert rec["rule"] == rule
    voxel_run = json.loads((out / "voxel" / "phase_000.0.json").read_text())
    if rule == "density-classes":
        assert {"lung", "cortical_bone"} <= set(voxel_run["materials"])
        return
    assert rec["hu_from"].startswith("the reference CT")
    for voxels in rec["voxels_per_phase"]:  # 16 voxels a slice; the mesh's voxels are water
        assert voxels["schneider_lung"] == 16 * 8 and voxels["schneider_marrow_bone10"] == 16 * 6
        assert sum(voxels.values()) == 16 * 30
    assert {"schneider_lung", "schneider_marrow_bone10"} <= set(voxel_run["compositions"])
    hybrid = json.loads((out / "phase_000.0.json").read_text())
    assert "schneider_lung" in hybrid["compositions"] and "lung" not in hybrid["materials"]


def test_run_dose4d_bins_the_phase_cts_of_a_4dct(d):
    series = PhaseSeries.read(None, d / "phases")
    ct = _ct()
    moved = ct.with_array(np.roll(np.asarray(ct.array), 1, axis=0))  # phase 2: slabs 1 slice on
    st = TransportSettings(n_histories=100, n_batches=2, physics="kerma")
    result = run_dose4d(series, Plan.from_toml(d / "plan.toml"), st, phase_ct=[ct, moved])
    rec = result.summary()["ct_materials"]
    assert rec["hu_from"] == "the phase CTs"
    assert [v["schneider_lung"] for v in rec["voxels_per_phase"]] == [16 * 8, 16 * 8]
    assert rec["voxels_per_phase"][1]["schneider_softtissus"] == 16 * 16
    with pytest.raises(OptionError, match="ct_materials must be one of"):
        run_dose4d(series, Plan.from_toml(d / "plan.toml"), st, phase_ct=[ct, moved],
                   ct_materials="hounsfield")


def test_phase_plans_give_every_voxel_run_the_bins(d):
    """The interplay path (a plan per phase): hybrid and voxel-only runs both get the bins."""
    series = PhaseSeries.read(None, d / "phases")
    plan, ct = Plan.from_toml(d / "plan.toml"), _ct()
    st = [TransportSettings(n_histories=100, n_batches=2, physics="kerma", stream=k)
          for k in range(2)]
    result = run_dose4d(series, plan, st[0], phase_ct=[ct, ct], phase_plans=[plan, plan],
                        phase_settings=st)
    for r in [*result.results, *result.voxel.results]:
        assert {"schneider_lung", "schneider_marrow_bone10"} <= set(r.record()["compositions"])
