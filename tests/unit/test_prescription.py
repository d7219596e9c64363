"""Prescriptions: DVH metrics by a naive reference, scaling of results, the dose CLI with
--rtplan and [prescription], and the "Gy per source photon" label without one."""

import json

import numpy as np
import pytest

from tetdose.core.image import Image, ImageGrid
from tetdose.core.io import read_image, write_image
from tetdose.dose.absolute import absolute_result
from tetdose.errors import PlanError
from tetdose.plan.prescription import (
    PER_PHOTON_UNIT,
    Prescription,
    dose_metric,
    scale_for,
)
from tetdose.plan.rt_plan import write_rt_plan
from tetdose.transport import Plan


def _naive_dxx(d, w, pct):
    """Smallest dose D such that the cells with dose ≥ D hold ≥ pct % of the weight."""
    for cand in sorted(d):
        if w[d >= cand].sum() < pct / 100 * w.sum() * (1 - 1e-12):
            break
        best = cand
    return best


def test_metrics_against_a_naive_reference():
    rng = np.random.default_rng(3)
    d, w = rng.uniform(1, 2, 200), rng.uniform(0.5, 1.5, 200)
    for pct in (95, 50, 2):
        assert dose_metric(d, w, f"D{pct}") == _naive_dxx(d, w, pct)
    assert dose_metric(d, w, "mean") == pytest.approx(np.dot(d, w) / w.sum())
    assert dose_metric(np.full(5, 3.0), np.ones(5), "D95") == 3.0
    with pytest.raises(PlanError, match="metric"):
        Prescription("tumour", 2.0, metric="V20")


def test_scale_makes_the_metric_equal_the_prescription():
    rng = np.random.default_rng(4)
    dose, mass = rng.uniform(1e-13, 3e-13, 100), rng.uniform(1, 2, 100)
    mask = np.arange(100) < 40
    rx = Prescription("tumour", 2.0, "D95", 30)
    s = scale_for(rx, dose, mass, mask)
    assert dose_metric(s * dose[mask], mass[mask], "D95") == pytest.approx(2.0)


@pytest.fixture(scope="module")
def water_ct(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("ct")
    grid = ImageGrid(np.array([-45.0, -45.0, -45.0]), np.full(3, 10.0), np.eye(3), (10, 10, 10))
    write_image(tmp / "ct.nrrd", Image(np.zeros(grid.shape, dtype=np.int16), grid))
    lab = np.ones(grid.shape, dtype=np.int16)
    lab[4:6, 4:6, 4:6] = 3  # tumour: the central 2×2×2 voxels
    write_image(tmp / "labels.nrrd", Image(lab, grid))
    return tmp


def _dose(tmp, *extra):
    from tetdose.cli import main

    return main(["dose", "--physics", "kerma",
                 "--ct", str(tmp / "ct.nrrd"), "--labels", str(tmp / "labels.nrrd"),
                 "--histories", "4000", "--batches", "4", "-q", *extra])


def test_cli_rtplan_with_prescription_gives_gy(water_ct, tmp_path):
    from tetdose.plan.beams import ControlPoint, LinacBeam

    plan = Plan(treatment_beams=(
        LinacBeam("AP", "6MV", (0, 0, 0), (ControlPoint(0, 0, 0, (-30, 30, -30, 30)),)),
        LinacBeam("LAT", "6MV", (0, 0, 0), (ControlPoint(90, 0, 0, (-30, 30, -30, 30)),))))
    write_rt_plan(plan, tmp_path / "plan.dcm")
    base = '[regions]\ntumour = 3\n[materials]\n1 = "water"\n3 = "water"\n'
    (tmp_path / "raw.toml").write_text(base)
    (tmp_path / "rx.toml").write_text(base + '[prescription]\nstructure = "tumour"\n'
                                      'dose_gy = 2.0\nmetric = "mean"\nfractions = 5\n')
    assert _dose(water_ct, "--plan", str(tmp_path / "rx.toml"), "--rtplan",
                 str(tmp_path / "plan.dcm"), "-o", str(tmp_path / "dose.nrrd")) == 0
    rec = json.loads((tmp_path / "dose.json").read_text())
    assert rec["units"]["dose"] == "Gy per fraction"
    assert rec["prescription"]["total_dose_gy"] == 10.0 and rec["prescription_scale"] > 1e10
    dose = read_image(tmp_path / "dose.nrrd").array
    lab = read_image(water_ct / "labels.nrrd").array
    assert dose[lab == 3].mean() == pytest.approx(2.0, rel=1e-5)  # equal voxel masses: mean
    # Without the prescription: the same run, per source photon, and said so.
    assert _dose(water_ct, "--plan", str(tmp_path / "raw.toml"), "--rtplan",
                 str(tmp_path / "plan.dcm"), "-o", str(tmp_path / "raw.nrrd")) == 0
    raw = json.loads((tmp_path / "raw.json").read_text())
    assert raw["units"]["dose"] == PER_PHOTON_UNIT
    assert raw["near_max_dose_gy"] * rec["prescription_scale"] == pytest.approx(
        rec["near_max_dose_gy"], rel=1e-9)


def test_absolute_result_needs_the_structure(water_ct):
    plan = Plan.from_dict({"beam": [{"type": "pencil", "energy_mev": 1.0,
                                     "position_mm": [0, 0, -100]}],
                           "prescription": {"structure": "ptv", "dose_gy": 2}})
    with pytest.raises(PlanError, match=r"\[regions\]"):
        absolute_result(None, plan, read_image(water_ct / "ct.nrrd"),
                         read_image(water_ct / "labels.nrrd"))


def test_structure_cells_and_centroid_on_a_mesh_and_a_world():
    from types import SimpleNamespace

    from tetdose.core.mesh import TetMesh
    from tetdose.plan.prescription import region_cells, region_centroid_mm

    pts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [3, 3, 3]], dtype=float)
    mesh = TetMesh(pts, np.array([[0, 1, 2, 3], [1, 2, 3, 4]]), np.array([3, 3]))
    vols, cents = mesh.volumes_mm3, mesh.centroids_mm
    np.testing.assert_allclose(region_centroid_mm(mesh, None, 3),
                               (vols[:, None] * cents).sum(0) / vols.sum())
    grid = ImageGrid(np.zeros(3), np.ones(3), np.eye(3), (4, 4, 4))
    lab = np.zeros(grid.shape, dtype=np.int16)
    lab[0, 0, 3] = 3
    world = SimpleNamespace(mesh=mesh, density=Image(np.ones(grid.shape), grid),
                            labels=Image(lab, grid))
    mask = region_cells(world, None, 3)  # the world's cells: tets first, then voxels
    assert mask.shape == (2 + 64,) and mask[:2].all() and mask[2:].sum() == 1 and mask[2 + 3]
    with pytest.raises(PlanError, match="no cells"):
        region_cells(mesh, None, 7)


def test_dose_result_is_immutable_and_with_extra_returns_a_new_one():
    from dataclasses import replace

    from tetdose.plan.prescription import PER_PHOTON_UNIT
    from tetdose.transport.history.result import COUNT_KEYS, DoseResult

    r = DoseResult(np.ones((2, 3)), np.array([5, 5]), np.ones(3), np.zeros((2, 5)),
                   np.zeros((2, len(COUNT_KEYS)), np.int64), 1.0, 0, "track_length", "mesh", 0.1, "0",
                   extra={"a": 1})
    with pytest.raises(TypeError, match="with_extra"):
        r.extra["b"] = 2
    with pytest.raises(TypeError, match="with_extra"):
        r.extra.update(b=2)
    r2 = r.with_extra(b=2, a=3)
    assert dict(r.extra) == {"a": 1} and dict(r2.extra) == {"a": 3, "b": 2}
    assert replace(r2, seed=1).extra == r2.extra
    assert r.record()["units"] == {"dose": PER_PHOTON_UNIT}
    assert r.with_extra(units={"dose": "Gy per fraction"}).record()["units"]["dose"] == \
        "Gy per fraction"
