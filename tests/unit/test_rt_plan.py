"""RT Plan: every control point read and written (static, step-and-shoot, sliding window, VMAT),
read → write → read exact, the sampled source against the control points, fraction groups, FFF,
refusals by name, and dciodvfy (dicom3tools) on the written files when it is installed."""

import shutil
import subprocess
import warnings

import numpy as np
import pydicom
import pytest

from tetdose._random import seed_for
from tetdose.errors import PlanError
from tetdose.plan import Plan
from tetdose.plan.beams import MLC, ControlPoint, LinacBeam, aperture_rectangles, beam_axes
from tetdose.plan.prescription import Prescription
from tetdose.plan.rt_plan import write_rt_plan
from tetdose.plan.segments import DynamicSegment
from tetdose.transport.run.settings import TransportSettings
from tetdose.transport.sources._sample import sample_source
from tetdose.transport.sources.arrays import source_arrays
from vmat_plan import BOUNDARIES_MM, write_vmat_plan

ISO = (12.5, -30.0, 40.0)
BOUNDS = [-30.0, -10.0, 10.0, 30.0]
DCIODVFY = shutil.which("dciodvfy")


def _plan():
    """Two static beams, a three-segment step-and-shoot beam (HFS and FFS), a sliding-window
    MLCY beam and a flattening-filter-free arc with a couch kick."""
    sns = []
    for k, (w0, w1) in enumerate(((0.0, 0.5), (0.5, 0.8), (0.8, 1.0))):
        mlc = MLC(BOUNDS, [-20 + 5 * k, -10, -5, 10 + k, 10, 25])
        sns += [ControlPoint(270.0, 15.0, 10.0, (-40, 40, -30, 30), mlc, w0),
                ControlPoint(270.0, 15.0, 10.0, (-40, 40, -30, 30), mlc, w1)]
    sliding = (ControlPoint(45, 0, 0, (-30, 30, -30, 30), MLC(BOUNDS, [-30] * 3 + [-25] * 3, "Y"),
                            0.0),
               ControlPoint(45, 0, 0, (-30, 30, -30, 30), MLC(BOUNDS, [20] * 3 + [30] * 3, "Y"),
                            100.0))
    arc = (ControlPoint(181, 0, 10, (-20, 20, -30, 30), None, 0.0, "CW"),
           ControlPoint(90, 0, 10, (-25, 20, -30, 30), None, 0.6, "CW"),
           ControlPoint(179, 0, 10, (-20, 20, -30, 30), None, 1.0))
    return Plan(treatment_beams=(
        LinacBeam("AP", "6MV", ISO, (ControlPoint(0, 0, 0, (-50, 50, -40, 40)),), meterset=100),
        LinacBeam("LAT", "10MV", ISO, (ControlPoint(90, 30, 0, (-20, 60, -10, 10)),),
                  sad_mm=800, patient_position="FFS", meterset=50),
        LinacBeam("SNS", "Co60", ISO, tuple(sns), meterset=80),
        LinacBeam("SW", "6MV", ISO, sliding, meterset=120),
        LinacBeam("ARC", "6MV", ISO, arc, meterset=200, fluence_mode="FFF")),
        prescription=Prescription("tumour", 2.0, fractions=30))


def _assert_same_beams(a_beams, b_beams, exact=False):
    """Same beams, control point by control point (a one-point static field is the pair 0 → 1
    of the same state); ``exact``: equal floats."""
    for a, b in zip(a_beams, b_beams, strict=True):
        assert (a.name, a.patient_position, a.sad_mm, a.meterset, a.fluence_mode) == \
            (b.name, b.patient_position, b.sad_mm, b.meterset, b.fluence_mode)
        np.testing.assert_array_equal(a.energies_mev, b.energies_mev)
        cps = a.control_points if len(a.control_points) > 1 else a.control_points * 2
        assert len(cps) == len(b.control_points)
        same = np.testing.assert_array_equal if exact else np.testing.assert_allclose
        for s, t in zip(cps, b.control_points, strict=True):
            same([s.gantry_deg % 360, s.collimator_deg % 360, s.couch_deg % 360],
                 [t.gantry_deg, t.collimator_deg, t.couch_deg])
            assert (s.gantry_rotation, s.collimator_rotation, s.couch_rotation) == \
                (t.gantry_rotation, t.collimator_rotation, t.couch_rotation)
            same(s.jaws_mm, t.jaws_mm)
            same(a.isocenter_at(s), b.isocenter_at(t))
            if len(a.control_points) > 1:
                same(s.meterset_weight, t.meterset_weight)
            assert (s.mlc is None) == (t.mlc is None)
            if s.mlc is not None:
                same(s.mlc.positions_mm, t.mlc.positions_mm)
                same(s.mlc.boundaries_mm, t.mlc.boundaries_mm)
                assert s.mlc.axis == t.mlc.axis


def test_round_trip_gives_the_same_control_points_and_sources(tmp_path):
    plan = _plan()
    path = write_rt_plan(plan, tmp_path / "plan.dcm")
    ds = pydicom.dcmread(path)
    assert ds.Modality == "RTPLAN" and len(ds.BeamSequence) == 5
    assert [b.BeamType for b in ds.BeamSequence] == ["STATIC", "STATIC", "STATIC", "DYNAMIC",
                                                     "DYNAMIC"]
    assert ds.BeamSequence[4].PrimaryFluenceModeSequence[0].FluenceModeID == "FFF"
    assert ds.FractionGroupSequence[0].NumberOfFractionsPlanned == 30
    with pytest.warns(UserWarning, match="flattening-filter-free"):
        back = Plan.from_rt_plan(path)
    _assert_same_beams(plan.treatment_beams, back.treatment_beams)
    # The flattened sources (what the kernel samples) agree too.
    assert [s.kind for s in back.sources] == ["linac"] * 5 + ["linac_dynamic"] * 3
    for s, t in zip(plan.sources, back.sources, strict=True):
        np.testing.assert_allclose(s.position_mm, t.position_mm, atol=1e-9)
        assert s.weight == pytest.approx(t.weight)


def test_vmat_plan_reads_writes_and_reads_back_exactly(tmp_path):
    """A two-arc VMAT plan of 91 control points per arc with a 120-leaf MLC, as a planning
    system writes it (carried-forward attributes), reads; written back and read again it gives
    the same floats."""
    path = write_vmat_plan(tmp_path / "vmat.dcm", iso=ISO)
    first = Plan.from_rt_plan(path)
    arc1, arc2 = first.treatment_beams
    assert len(arc1.control_points) == 91 and arc1.meterset == 310.5
    assert arc1.control_points[0].gantry_rotation == "CW"
    assert arc2.control_points[45].gantry_rotation == "CC"  # carried forward
    np.testing.assert_array_equal(arc1.control_points[-1].mlc.boundaries_mm, BOUNDARIES_MM)
    assert [c.collimator_deg for c in arc1.control_points] == [30.0] * 91
    np.testing.assert_array_equal(arc1.control_points[90].jaws_mm, [-45, 45, -80, 80])
    turns = [s.turns_deg[0] for s in first.sources]
    assert len(turns) == 180 and sum(turns[:90]) == pytest.approx(358.0)
    assert sum(turns[90:]) == pytest.approx(-358.0)
    again = Plan.from_rt_plan(write_rt_plan(first, tmp_path / "again.dcm"))
    _assert_same_beams(first.treatment_beams, again.treatment_beams, exact=True)
    for s, t in zip(first.sources, again.sources, strict=True):
        assert (s.weight, s.turns_deg, s.max_area_mm2) == (t.weight, t.turns_deg, t.max_area_mm2)


def _inside(rects, a1, a2, tol=1e-6):
    return bool(np.any((rects[:, 0] - tol <= a1) & (a1 <= rects[:, 1] + tol)
                       & (rects[:, 2] - tol <= a2) & (a2 <= rects[:, 3] + tol)))


def test_vmat_photons_start_on_the_arc_and_pass_the_leaves_of_their_gantry_angle(tmp_path):
    """Every sampled photon of the VMAT plan starts on the arc (SAD from the isocentre, in the
    gantry plane), and crosses the isocentre plane inside the MLC aperture interpolated at its
    gantry angle (in one of the two arcs)."""
    plan = Plan.from_rt_plan(write_vmat_plan(tmp_path / "vmat.dcm", iso=ISO))
    src = source_arrays(plan, TransportSettings(n_histories=10, n_batches=2, physics="kerma"))
    segs = plan.sources
    starts = np.array([s.start.gantry_deg for s in segs])
    for i in range(3000):
        _, _e, x, y, z, u, v, w = sample_source(src, np.uint64(seed_for(3, 0, i)), np.empty(0))
        p, d = np.array([x, y, z]) - ISO, np.array([u, v, w])
        assert np.linalg.norm(p) == pytest.approx(1000.0) and abs(p[2]) < 1e-9  # HFS: gantry plane
        g = np.degrees(np.arctan2(p[0], -p[1])) % 360.0
        # the segment whose arc holds g: ARC1 181 → 179 CW, ARC2 back CC (try both arcs)
        ok = False
        for arc in (range(90), range(90, 180)):
            for k in arc:
                s: DynamicSegment = segs[k]
                t = ((g - starts[k]) * np.sign(s.turns_deg[0]) % 360.0) / abs(s.turns_deg[0])
                if t <= 1.0 + 1e-9:
                    ax = s.axes_at(t)
                    hit = p + 1000.0 / np.dot(d, -ax[2]) * d
                    ok = ok or _inside(s.aperture_at(t), hit @ ax[0], hit @ ax[1])
                    break
        assert ok


def test_sampled_static_sources_match_the_control_points(tmp_path):
    """Static beams and step-and-shoot segments: every photon starts at iso + SAD·Z_b and crosses
    the isocentre plane inside jaws ∩ MLC; beams are drawn in proportion to meterset × open area
    / SAD² (equal fluence per MU)."""
    plan = Plan(treatment_beams=_plan().treatment_beams[:3])
    back = Plan.from_rt_plan(write_rt_plan(plan, tmp_path / "plan.dcm"))
    src = source_arrays(back, TransportSettings(n_histories=10, n_batches=2, physics="kerma"))
    expected = []
    for beam in back.treatment_beams:
        cps = beam.control_points
        seg = cps[0]
        ax = beam_axes(seg.gantry_deg, seg.collimator_deg, seg.couch_deg, beam.patient_position)
        rects = np.concatenate([aperture_rectangles(s.jaws_mm, s.mlc) for s in cps])
        mu_area = sum((b.meterset_weight - a.meterset_weight) * beam.meterset
                      * _area(aperture_rectangles(a.jaws_mm, a.mlc))
                      for a, b in zip(cps[:-1], cps[1:], strict=True))
        expected.append([np.asarray(ISO) + beam.sad_mm * ax[2], ax, beam.sad_mm, rects,
                         mu_area / beam.sad_mm**2])
    norm = sum(e[4] for e in expected)
    n, counts = 6000, np.zeros(3)
    for i in range(n):
        _, _e, x, y, z, u, v, w = sample_source(src, np.uint64(seed_for(3, 0, i)), np.empty(0))
        p, d = np.array([x, y, z]), np.array([u, v, w])
        k = int(np.argmin([np.linalg.norm(p - e[0]) for e in expected]))
        src_pos, ax, sad, rects, _ = expected[k]
        np.testing.assert_allclose(p, src_pos, atol=1e-9)
        hit = p + sad / np.dot(d, -ax[2]) * d - np.asarray(ISO)
        assert _inside(rects, hit @ ax[0], hit @ ax[1])
        counts[k] += 1
    for c, e in zip(counts, expected, strict=True):
        q = e[4] / norm
        assert abs(c / n - q) < 4 * np.sqrt(q * (1 - q) / n)


def _area(rects):
    return float(np.sum((rects[:, 1] - rects[:, 0]) * (rects[:, 3] - rects[:, 2])))


def _modified(tmp_path, change, name="m.dcm"):
    ds = pydicom.dcmread(write_rt_plan(Plan(treatment_beams=_plan().treatment_beams[:3]),
                                       tmp_path / "plan.dcm"))
    change(ds)
    ds.save_as(tmp_path / name)
    return tmp_path / name


def _set(path, value):
    def change(ds):
        obj = ds
        *parts, last = path
        for p in parts:
            obj = obj[p] if isinstance(p, int) else getattr(obj, p)
        if value is None:
            delattr(obj, last)
        else:
            setattr(obj, last, value)
    return change


def _add_device(kind, beam=0):
    def change(ds):
        dev = pydicom.Dataset()
        dev.RTBeamLimitingDeviceType, dev.NumberOfLeafJawPairs = kind, 2
        dev.LeafPositionBoundaries = ["-10", "0", "10"]
        ds.BeamSequence[beam].BeamLimitingDeviceSequence.append(dev)
    return change


@pytest.mark.parametrize(("change", "message"), [
    (_set(("BeamSequence", 1, "RadiationType"), "ELECTRON"), "'LAT' is ELECTRON: only photon"),
    (_set(("BeamSequence", 0, "NumberOfWedges"), 1), "'AP' has wedges"),
    (_set(("BeamSequence", 0, "NumberOfBlocks"), 2), "'AP' has blocks"),
    (_set(("BeamSequence", 0, "NumberOfCompensators"), 1), "'AP' has compensators"),
    (_set(("BeamSequence", 0, "NumberOfBoli"), 1), "'AP' has boli"),
    (_set(("BeamSequence", 0, "ApplicatorSequence"), [pydicom.Dataset()]), "'AP' has an applic"),
    (_add_device("MLCX1"), "'AP': beam limiting device MLCX1 is not modelled"),
    (_add_device("MLCY", beam=2), "'SNS' has two MLCs .MLCX and MLCY."),
    (_set(("BeamSequence", 0, "ControlPointSequence"), []), "'AP' has no ControlPointSequence"),
    (_set(("BeamSequence", 0, "ControlPointSequence", 1, "CumulativeMetersetWeight"), None),
     "'AP' control point 1 has no CumulativeMetersetWeight"),
    (_set(("BeamSequence", 2, "BeamLimitingDeviceSequence", 2, "LeafPositionBoundaries"), None),
     "'SNS': MLCX has no LeafPositionBoundaries"),
    (_set(("FractionGroupSequence", 0, "ReferencedBeamSequence", 0, "BeamMeterset"), "0"),
     "'AP': BeamMeterset = 0 MU"),
    (_set(("FractionGroupSequence", 0, "ReferencedBeamSequence", 1, "BeamMeterset"), "-5"),
     "'LAT': BeamMeterset = -5 MU"),
    (_set(("FractionGroupSequence", 0, "ReferencedBeamSequence", 0, "BeamMeterset"), None),
     "'AP': the fraction group gives no BeamMeterset"),
    (_set(("BeamSequence", 0, "SourceAxisDistance"), "400"), "'AP': SourceAxisDistance = 400"),
    (_set(("BeamSequence", 0, "ControlPointSequence", 0, "TableTopPitchAngle"), 2.0),
     "'AP' control point 0 has TableTopPitchAngle 2"),
    (_set(("BeamSequence", 0, "ControlPointSequence", 0, "NominalBeamEnergy"), "8"),
     "'AP': NominalBeamEnergy 8 MV has no shipped spectrum"),
    (_set(("BeamSequence", 0, "ControlPointSequence", 0, "NominalBeamEnergy"), "18"),
     "'AP': no citable 18MV"),
    (_set(("BeamSequence", 0, "ControlPointSequence", 1, "NominalBeamEnergy"), "10"),
     "'AP' control point 1 changes NominalBeamEnergy"),
    (_set(("BeamSequence", 0, "ControlPointSequence", 0, "IsocenterPosition"), None),
     "'AP' control point 0 .the first. lacks"),
    (_set(("BeamSequence", 0, "FinalCumulativeMetersetWeight"), "2"),
     "'AP': FinalCumulativeMetersetWeight 2 differs"),
    (_set(("BeamSequence", 0, "PrimaryFluenceModeSequence", 0, "FluenceMode"), "NON_STANDARD"),
     "'AP': fluence mode"),
    (_set(("PatientSetupSequence", 0, "PatientPosition"), "HFDL"), "patient position 'HFDL'"),
    (_set(("FractionGroupSequence",), None), "no FractionGroupSequence"),
])
def test_refuses_by_name_what_it_cannot_model_or_read(tmp_path, change, message):
    path = _modified(tmp_path, change)
    with pytest.raises(PlanError, match=message) as info:
        Plan.from_rt_plan(path)
    assert "\n" not in str(info.value)


def test_ion_and_brachy_plans_are_refused(tmp_path):
    def ion(ds):
        ds.IonBeamSequence = ds.BeamSequence
        del ds.BeamSequence

    with pytest.raises(PlanError, match="RT Ion Plan"):
        Plan.from_rt_plan(_modified(tmp_path, ion))
    with pytest.raises(PlanError, match="brachytherapy"):
        Plan.from_rt_plan(_modified(tmp_path, _set(("BrachyTreatmentType",), "HDR")))


def test_fraction_groups_are_chosen_by_number(tmp_path):
    """Two fraction groups (25 fractions of AP+LAT, 5 of SNS): without a choice the error lists
    them; --fraction-group / fraction_group picks one, its beams and its BeamMeterset."""
    def two_groups(ds):
        g1 = ds.FractionGroupSequence[0]
        g2 = pydicom.Dataset()
        g2.FractionGroupNumber, g2.NumberOfFractionsPlanned, g2.NumberOfBeams = 2, 5, 1
        g2.NumberOfBrachyApplicationSetups = 0
        rb = pydicom.Dataset()
        rb.ReferencedBeamNumber, rb.BeamMeterset = 3, "42.5"
        g2.ReferencedBeamSequence = [rb]
        g1.NumberOfFractionsPlanned, g1.NumberOfBeams = 25, 2
        g1.ReferencedBeamSequence = g1.ReferencedBeamSequence[:2]
        ds.FractionGroupSequence.append(g2)

    path = _modified(tmp_path, two_groups)
    with pytest.raises(PlanError, match=r"2 fraction groups \(1: 25 fractions, beams \[1, 2\]; "
                                        r"2: 5 fractions, beams \[3\]\).*--fraction-group"):
        Plan.from_rt_plan(path)
    assert [b.name for b in Plan.from_rt_plan(path, 1).treatment_beams] == ["AP", "LAT"]
    (sns,) = Plan.from_rt_plan(path, 2).treatment_beams
    assert (sns.name, sns.meterset) == ("SNS", 42.5)
    with pytest.raises(PlanError, match="no fraction group 3"):
        Plan.from_rt_plan(path, 3)
    (tmp_path / "plan.toml").write_text(f'rtplan = "{path.name}"\nfraction_group = 2\n')
    assert [b.name for b in Plan.from_toml(tmp_path / "plan.toml").treatment_beams] == ["SNS"]
    from tetdose.cli import _dose

    assert [b.name for b in _dose.load_plan(None, path, 1).treatment_beams] == ["AP", "LAT"]
    with pytest.raises(PlanError, match="of which RT Plan"):
        Plan.from_dict({"beam": [{"type": "linac", "spectrum": "6MV",
                                  "isocenter_mm": [0, 0, 0]}]}, fraction_group=1)


def test_static_beam_type_ignores_rotation_directions(tmp_path):
    """A STATIC beam does not move while on: a rotation direction CW between equal angles (a
    full turn in a DYNAMIC beam, C.8.8.14.8) is no turn. In a DYNAMIC beam an angle the later
    control point omits is unchanged (no turn); stated equal with CW it is a full turn, said."""
    def cw(ds):
        ds.BeamSequence[0].ControlPointSequence[0].GantryRotationDirection = "CW"

    def dynamic(ds):
        cw(ds)
        ds.BeamSequence[0].BeamType = "DYNAMIC"

    def stated(ds):
        dynamic(ds)
        ds.BeamSequence[0].ControlPointSequence[1].GantryAngle = "0"

    (ap,) = Plan.from_rt_plan(_modified(tmp_path, cw)).sources[:1]
    assert ap.kind == "linac"
    assert Plan.from_rt_plan(_modified(tmp_path, dynamic, "d.dcm")).sources[0].kind == "linac"
    with pytest.warns(UserWarning, match="'AP' turns the gantry a full 360° CW between control "
                      "points 0 and 1"):
        turned = Plan.from_rt_plan(_modified(tmp_path, stated, "s.dcm"))
    assert turned.sources[0].turns_deg == (360.0, 0.0, 0.0)
    # written back, the full turn keeps its stated angles (an omitted one would read as still)
    with pytest.warns(UserWarning, match="full 360°"):
        again = Plan.from_rt_plan(write_rt_plan(Plan(treatment_beams=turned.treatment_beams[:1]),
                                                tmp_path / "again.dcm"))
    assert again.sources[0].turns_deg == (360.0, 0.0, 0.0)


def _sliding_window(tmp_path, name, *, gantry_in_later=None, direction="CW", n=5):
    """A fixed-gantry (30°) sliding-window MLCX beam of ``n`` control points whose first says
    GantryRotationDirection ``direction``; the later ones carry GantryAngle
    ``gantry_in_later`` (None: omitted, as DICOM allows for an unchanged angle)."""
    cps = []
    for k in range(n):
        lead = -30.0 + 50.0 * k / (n - 1)
        mlc = MLC(BOUNDS, [lead - 10.0] * 3 + [lead] * 3)
        cps.append(ControlPoint(30.0, 10.0, 5.0, (-40, 40, -30, 30), mlc, k / (n - 1)))
    path = write_rt_plan(Plan(treatment_beams=(LinacBeam("SW", "6MV", ISO, tuple(cps),
                                                         meterset=100),)), tmp_path / name)
    ds = pydicom.dcmread(path)
    seq = ds.BeamSequence[0].ControlPointSequence
    seq[0].GantryRotationDirection = direction
    for cp in seq[1:]:
        assert "GantryAngle" not in cp and "IsocenterPosition" not in cp
        if gantry_in_later is not None:
            cp.GantryAngle = gantry_in_later
    ds.save_as(path)
    return path


def test_fixed_gantry_sliding_window_with_cw_and_no_later_angles_is_a_fixed_beam(tmp_path):
    """Issue 27: control point 0 says CW, later control points omit the gantry angle (DICOM: it
    is unchanged); the beam's segments and every sampled photon are those of the same beam with
    direction NONE, and the photons all start at gantry 30°."""
    omitted = Plan.from_rt_plan(_sliding_window(tmp_path, "cw.dcm"))
    explicit = Plan.from_rt_plan(_sliding_window(tmp_path, "none.dcm", direction="NONE"))
    assert [s.turns_deg for s in omitted.sources] == [(0.0, 0.0, 0.0)] * 4
    for s, t in zip(omitted.sources, explicit.sources, strict=True):
        assert (s.kind, s.weight, s.mean_area_mm2) == (t.kind, t.weight, t.mean_area_mm2)
    arrays = [source_arrays(p, TransportSettings(n_histories=10, n_batches=2, physics="kerma"))
              for p in (omitted, explicit)]
    source = np.asarray(ISO) + 1000.0 * beam_axes(30.0, 10.0, 5.0)[2]
    for i in range(300):
        a, b = (np.array(sample_source(s, np.uint64(seed_for(5, 0, i)), np.empty(0))[2:]) for s in arrays)
        np.testing.assert_array_equal(a, b)
        np.testing.assert_allclose(a[:3], source, atol=1e-9)


def test_contradictory_rotation_directions_are_read_and_said_or_refused(tmp_path):
    """CW with every angle stated equal: a full turn per segment (C.8.8.14.8) — more than a
    linac turns, refused with the fix; NONE with a changing angle: the shorter turn, said."""
    with pytest.raises(PlanError, match="'SW'.*turn the gantry through 1440° one way.*NONE"):
        Plan.from_rt_plan(_sliding_window(tmp_path, "cw.dcm", gantry_in_later="30"))
    with pytest.warns(UserWarning, match="rotation direction NONE but the angle moves 30° → 40°"):
        moved = Plan.from_rt_plan(_sliding_window(tmp_path, "none.dcm", gantry_in_later="40",
                                                  direction="NONE", n=2))
    assert moved.sources[0].turns_deg == (10.0, 0.0, 0.0)


def test_rtplan_key_in_plan_toml(tmp_path):
    write_rt_plan(Plan(treatment_beams=_plan().treatment_beams[:3]), tmp_path / "plan.dcm")
    (tmp_path / "plan.toml").write_text('rtplan = "plan.dcm"\n[materials]\n1 = "water"\n')
    plan = Plan.from_toml(tmp_path / "plan.toml")
    assert [b.name for b in plan.treatment_beams] == ["AP", "LAT", "SNS"]
    assert plan.materials == {1: "water"}


def test_arc_control_points_carry_forward_and_rotate(tmp_path):
    """A 3-control-point arc 0° → 20° → 40° CW (weights 0, 0.25, 1): two dynamic segments
    turning 20° each with 25 and 75 % of the MU; jaws and isocentre given only at the first
    control point apply to all."""
    path = write_rt_plan(Plan(treatment_beams=_plan().treatment_beams[:1]), tmp_path / "p.dcm")
    ds = pydicom.dcmread(path)
    beam = ds.BeamSequence[0]
    cps = beam.ControlPointSequence
    cps[0].GantryRotationDirection = "CW"
    cps[1].GantryAngle, cps[1].CumulativeMetersetWeight = "20", "0.25"
    assert "BeamLimitingDevicePositionSequence" not in cps[1]  # written at the first only
    extra = pydicom.Dataset()
    extra.ControlPointIndex, extra.GantryAngle, extra.CumulativeMetersetWeight = 2, "40", "1"
    cps.append(extra)
    beam.NumberOfControlPoints, beam.BeamType = 3, "DYNAMIC"
    ds.save_as(tmp_path / "arc.dcm")
    arc = Plan.from_rt_plan(tmp_path / "arc.dcm")
    assert [s.turns_deg[0] for s in arc.sources] == pytest.approx([20.0, 20.0])
    assert [s.meterset for s in arc.sources] == pytest.approx([25.0, 75.0])
    for c in arc.treatment_beams[0].control_points:
        np.testing.assert_allclose(c.jaws_mm, [-50, 50, -40, 40])
    np.testing.assert_allclose(arc.treatment_beams[0].isocenter_mm, ISO)


def _dciodvfy_errors(path):
    out = subprocess.run([DCIODVFY, str(path)], capture_output=True, text=True)
    return [ln for ln in (out.stdout + out.stderr).splitlines() if ln.startswith("Error")]


@pytest.mark.skipif(DCIODVFY is None, reason="dciodvfy (dicom3tools) not installed")
def test_written_plans_pass_dciodvfy(tmp_path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        vmat = Plan.from_rt_plan(write_vmat_plan(tmp_path / "vmat.dcm"))
    assert _dciodvfy_errors(tmp_path / "vmat.dcm") == []  # the test's plan is to the standard
    assert _dciodvfy_errors(write_rt_plan(_plan(), tmp_path / "plan.dcm")) == []
    assert _dciodvfy_errors(write_rt_plan(vmat, tmp_path / "vmat_out.dcm")) == []
