"""RT Plan write → read round trip, control-point geometry of the sampled source, refusals,
and dciodvfy (dicom3tools) on the written file when it is installed."""

import shutil
import subprocess

import numpy as np
import pydicom
import pytest

from tetdose._random import seed_for
from tetdose.errors import PlanError
from tetdose.plan.beams import MLC, ControlPoint, LinacBeam, aperture_rectangles, beam_axes
from tetdose.plan.prescription import Prescription
from tetdose.plan.rt_plan import write_rt_plan
from tetdose.transport import Plan, TransportSettings
from tetdose.transport.sources._sample import sample_source
from tetdose.transport.sources.arrays import source_arrays

ISO = (12.5, -30.0, 40.0)
BOUNDS = [-30.0, -10.0, 10.0, 30.0]


def _plan():
    """Two static beams and a three-segment step-and-shoot beam (HFS and FFS)."""
    sns = tuple(ControlPoint(270.0, 15.0, 10.0, (-40, 40, -30, 30),
                             MLC(BOUNDS, [-20 + 5 * k, -10, -5, 10 + k, 10, 25]), w)
                for k, w in enumerate((0.5, 0.3, 0.2)))
    return Plan(treatment_beams=(
        LinacBeam("AP", "6MV", ISO, (ControlPoint(0, 0, 0, (-50, 50, -40, 40)),), meterset=100),
        LinacBeam("LAT", "10MV", ISO, (ControlPoint(90, 30, 0, (-20, 60, -10, 10)),),
                  sad_mm=800, patient_position="FFS", meterset=50),
        LinacBeam("SNS", "Co60", ISO, sns, meterset=80)),
        prescription=Prescription("tumour", 2.0, fractions=30))


def test_round_trip_gives_the_same_beams(tmp_path):
    plan = _plan()
    path = write_rt_plan(plan, tmp_path / "plan.dcm")
    ds = pydicom.dcmread(path)
    assert ds.Modality == "RTPLAN" and len(ds.BeamSequence) == 3
    assert ds.FractionGroupSequence[0].NumberOfFractionsPlanned == 30
    back = Plan.from_rt_plan(path)
    for a, b in zip(plan.treatment_beams, back.treatment_beams, strict=True):
        assert (a.name, a.patient_position, a.sad_mm, a.meterset) == \
            (b.name, b.patient_position, b.sad_mm, b.meterset)
        np.testing.assert_allclose(a.isocenter_mm, b.isocenter_mm)
        np.testing.assert_allclose(a.energies_mev, b.energies_mev)
        assert len(a.segments) == len(b.segments)
        for s, t in zip(a.segments, b.segments, strict=True):
            assert (s.gantry_deg, s.collimator_deg, s.couch_deg) == \
                pytest.approx((t.gantry_deg, t.collimator_deg, t.couch_deg))
            np.testing.assert_allclose(s.jaws_mm, t.jaws_mm)
            assert s.meterset_fraction / sum(x.meterset_fraction for x in a.segments) == \
                pytest.approx(t.meterset_fraction)
            if s.mlc is not None:
                np.testing.assert_allclose(s.mlc.positions_mm, t.mlc.positions_mm)
                np.testing.assert_allclose(s.mlc.boundaries_mm, t.mlc.boundaries_mm)
    # The flattened sources (what the kernel samples) agree too.
    for s, t in zip(plan.sources, back.sources, strict=True):
        np.testing.assert_allclose(s.position_mm, t.position_mm, atol=1e-9)
        np.testing.assert_allclose(s.aperture_mm, t.aperture_mm)
        assert s.weight == pytest.approx(t.weight)


def _area(seg):
    """Open area [mm²] of a segment: jaws ∩ each leaf pair, by hand."""
    x1, x2, y1, y2 = seg.jaws_mm
    if seg.mlc is None:
        return (x2 - x1) * (y2 - y1)
    b, p = seg.mlc.boundaries_mm, seg.mlc.positions_mm
    n = len(b) - 1
    return sum(max(0.0, min(x2, p[n + i]) - max(x1, p[i]))
               * max(0.0, min(y2, b[i + 1]) - max(y1, b[i])) for i in range(n))


def _inside(rects, a1, a2, tol=1e-9):
    return bool(np.any((rects[:, 0] - tol <= a1) & (a1 <= rects[:, 1] + tol)
                       & (rects[:, 2] - tol <= a2) & (a2 <= rects[:, 3] + tol)))


def test_sampled_sources_match_the_control_points(tmp_path):
    """Exact geometry: every sampled photon starts at iso + SAD·Z_b of its beam's control points
    and crosses the isocentre plane inside their jaws ∩ MLC; segments are drawn in proportion to
    meterset × open area / SAD² (equal fluence per MU). (The step-and-shoot segments share one
    source position: their union.)"""
    back = Plan.from_rt_plan(write_rt_plan(_plan(), tmp_path / "plan.dcm"))
    src = source_arrays(back, TransportSettings(n_histories=10, n_batches=2, physics="kerma"))
    expected = []  # per beam: source position, axes, sad, union of segment apertures, MU share
    for beam in back.treatment_beams:
        seg = beam.segments[0]
        ax = beam_axes(seg.gantry_deg, seg.collimator_deg, seg.couch_deg, beam.patient_position)
        rects = np.concatenate([aperture_rectangles(s.jaws_mm, s.mlc) for s in beam.segments])
        total = sum(s.meterset_fraction for s in beam.segments)
        mu_area = sum(s.meterset_fraction / total * beam.meterset * _area(s)
                      for s in beam.segments)
        expected.append([np.asarray(ISO) + beam.sad_mm * ax[2], ax, beam.sad_mm, rects,
                         mu_area / beam.sad_mm**2])
    norm = sum(e[4] for e in expected)
    for e in expected:
        e[4] /= norm
    n = 6000
    counts = np.zeros(3)
    for i in range(n):
        _, _e, x, y, z, u, v, w = sample_source(src, np.uint64(seed_for(3, 0, i)))
        p, d = np.array([x, y, z]), np.array([u, v, w])
        k = int(np.argmin([np.linalg.norm(p - e[0]) for e in expected]))
        src_pos, ax, sad, rects, _ = expected[k]
        np.testing.assert_allclose(p, src_pos, atol=1e-9)
        hit = p + sad / np.dot(d, -ax[2]) * d - np.asarray(ISO)
        assert _inside(rects, hit @ ax[0], hit @ ax[1])
        counts[k] += 1
    for c, (*_, q) in zip(counts, expected, strict=True):
        assert abs(c / n - q) < 4 * np.sqrt(q * (1 - q) / n)


def test_refuses_what_it_cannot_model(tmp_path):
    path = write_rt_plan(_plan(), tmp_path / "plan.dcm")
    ds = pydicom.dcmread(path)
    ds.BeamSequence[1].RadiationType = "ELECTRON"
    ds.save_as(tmp_path / "e.dcm")
    with pytest.raises(PlanError, match="ELECTRON: only photon"):
        Plan.from_rt_plan(tmp_path / "e.dcm")
    ds = pydicom.dcmread(path)
    ds.BeamSequence[0].NumberOfWedges = 1
    ds.save_as(tmp_path / "w.dcm")
    with pytest.raises(PlanError, match="wedges"):
        Plan.from_rt_plan(tmp_path / "w.dcm")


def test_rtplan_key_in_plan_toml(tmp_path):
    write_rt_plan(_plan(), tmp_path / "plan.dcm")
    (tmp_path / "plan.toml").write_text('rtplan = "plan.dcm"\n[materials]\n1 = "water"\n')
    plan = Plan.from_toml(tmp_path / "plan.toml")
    assert [b.name for b in plan.treatment_beams] == ["AP", "LAT", "SNS"]
    assert plan.materials == {1: "water"}


@pytest.mark.skipif(shutil.which("dciodvfy") is None, reason="dciodvfy (make tools) not installed")
def test_written_plan_passes_dciodvfy(tmp_path):
    path = write_rt_plan(_plan(), tmp_path / "plan.dcm")
    out = subprocess.run(["dciodvfy", str(path)], capture_output=True, text=True)
    errors = [ln for ln in (out.stdout + out.stderr).splitlines() if ln.startswith("Error")]
    assert errors == []


def test_arc_is_sampled_at_its_control_points_and_attributes_carry_forward(tmp_path):
    """A 3-control-point arc 0° → 20° → 40° (weights 0, 0.25, 1) becomes two segments at the
    mean angles 10° and 30° with ΔW 0.25 and 0.75; jaws and isocentre given only at the first
    control point apply to all."""
    path = write_rt_plan(_plan(), tmp_path / "plan.dcm")
    ds = pydicom.dcmread(path)
    beam = ds.BeamSequence[0]
    cps = beam.ControlPointSequence
    cps[1].GantryAngle, cps[1].CumulativeMetersetWeight = "20", "0.25"
    del cps[1].BeamLimitingDevicePositionSequence
    extra = pydicom.Dataset()
    extra.ControlPointIndex, extra.GantryAngle, extra.CumulativeMetersetWeight = 2, "40", "1"
    cps.append(extra)
    beam.NumberOfControlPoints, beam.BeamType = 3, "DYNAMIC"
    ds.save_as(tmp_path / "arc.dcm")
    arc = Plan.from_rt_plan(tmp_path / "arc.dcm").treatment_beams[0]
    assert [s.gantry_deg for s in arc.segments] == pytest.approx([10.0, 30.0])
    assert [s.meterset_fraction for s in arc.segments] == pytest.approx([0.25, 0.75])
    for s in arc.segments:
        np.testing.assert_allclose(s.jaws_mm, [-50, 50, -40, 40])
    np.testing.assert_allclose(arc.isocenter_mm, ISO)
