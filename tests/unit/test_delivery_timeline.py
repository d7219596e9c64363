"""Delivery in time (issue 31), exactly and without transport: the timeline of control points,
the breathing trace / regular cycle, and the MU and photons each phase gets."""

from __future__ import annotations

import numpy as np
import pytest

from tetdose.errors import OptionError, PlanError
from tetdose.motion.trace import BreathingTrace, amplitude_phase, regular_cycle
from tetdose.plan.delivery import delivery_timeline, rt_plan_dose_rates
from tetdose.plan.model import Plan
from tetdose.plan.phase_split import split_by_phase
from tetdose.plan.segments import DynamicSegment

PCT = np.arange(0.0, 100.0, 10.0)
LEAVES = {"boundaries_mm": [-20.0, -10.0, 0.0, 10.0, 20.0]}


def vmat(**machine) -> Plan:
    """Two arcs: 358° CW with a leaf sweep, then a static-aperture arc back, 250 MU each."""
    return Plan.from_dict({"beam": [
        {"type": "linac", "name": "A1", "spectrum": "6MV", "isocenter_mm": [0.0, 0.0, 0.0],
         "jaws_mm": [-20.0, 20.0, -20.0, 20.0], "mlc": LEAVES, "weight": 250.0, **machine,
         "control_points": [
             {"meterset_weight": 0.0, "gantry_deg": 181.0, "gantry_direction": "CW",
              "mlc": [-10.0, -15.0, -15.0, -10.0, 10.0, 15.0, 15.0, 10.0]},
             {"meterset_weight": 0.6, "gantry_deg": 0.0,
              "mlc": [-5.0, -20.0, -20.0, -5.0, 5.0, 20.0, 20.0, 5.0]},
             {"meterset_weight": 1.0, "gantry_deg": 179.0,
              "mlc": [0.0, -10.0, -10.0, 0.0, 12.0, 10.0, 10.0, 12.0]}]},
        {"type": "linac", "name": "A2", "spectrum": "6MV", "isocenter_mm": [0.0, 0.0, 0.0],
         "jaws_mm": [-20.0, 20.0, -20.0, 20.0], "weight": 250.0, **machine,
         "arc": {"start_deg": 179.0, "stop_deg": 181.0, "direction": "CC"}}]})


def test_timeline_takes_the_slowest_limit():
    # A1: 179° + 179° at 6 °/s = 29.8 s each > 150 MU and 100 MU at 600 MU/min (15 s, 10 s)
    tl = delivery_timeline(vmat().treatment_beams)
    a1, a2 = tl.beams
    np.testing.assert_allclose(np.diff(a1.times_s), [179.0 / 6.0, 179.0 / 6.0])
    np.testing.assert_allclose(a1.mu, [150.0, 100.0])
    assert a2.times_s[0] == a1.times_s[-1]  # default gap 0
    np.testing.assert_allclose(np.diff(a2.times_s), [358.0 / 6.0])
    # dose-rate bound: 100 MU/min → 90 s and 60 s; leaf bound 5 mm, 10 mm at 0.1 mm/s
    slow = delivery_timeline(vmat(dose_rate_mu_per_min=100.0, beam_gap_s=30.0).treatment_beams)
    np.testing.assert_allclose(np.diff(slow.beams[0].times_s), [90.0, 60.0])
    assert slow.beams[1].times_s[0] == pytest.approx(150.0 + 30.0)
    leaf = delivery_timeline(vmat(max_leaf_mm_per_s=0.1).treatment_beams)
    np.testing.assert_allclose(np.diff(leaf.beams[0].times_s), [50.0, 100.0])
    fast = delivery_timeline(vmat(max_gantry_deg_per_s=1000.0).treatment_beams)
    np.testing.assert_allclose(np.diff(fast.beams[0].times_s), [15.0, 10.0])
    assert fast.beam_on_s == pytest.approx(50.0)
    assert fast.record()["mu"] == pytest.approx(500.0)


def test_static_beam_and_step_and_shoot_gaps():
    plan = Plan.from_dict({"beam": [{
        "type": "linac", "spectrum": "6MV", "isocenter_mm": [0.0, 0.0, 0.0], "mlc": LEAVES,
        "jaws_mm": [-20.0, 20.0, -20.0, 20.0], "weight": 120.0, "max_leaf_mm_per_s": 20.0,
        "control_points": [
            {"meterset_weight": 0.0, "mlc": [-5.0] * 4 + [5.0] * 4},
            {"meterset_weight": 0.5},
            {"meterset_weight": 0.5, "mlc": [-15.0] * 4 + [15.0] * 4},   # leaves move, beam off
            {"meterset_weight": 1.0}]},
        {"type": "linac", "spectrum": "6MV", "isocenter_mm": [0.0, 0.0, 0.0], "weight": 60.0}]})
    a, b = delivery_timeline(plan.treatment_beams).beams
    np.testing.assert_allclose(np.diff(a.times_s), [6.0, 0.5, 6.0])  # 10 mm at 20 mm/s
    np.testing.assert_allclose(a.mu, [60.0, 0.0, 60.0])
    assert a.beam_on_s == pytest.approx(12.0)
    np.testing.assert_allclose(np.diff(b.times_s), [6.0])  # one control point: a static field


def test_rt_plan_dose_rate_carries_forward(tmp_path):
    pydicom = pytest.importorskip("pydicom")
    from tetdose.plan.rt_plan import write_rt_plan

    plan = Plan.from_dict({"beam": [{
        "type": "linac", "name": "ARC", "spectrum": "6MV", "isocenter_mm": [0.0, 0.0, 0.0],
        "weight": 200.0, "control_points": [
            {"meterset_weight": 0.0, "gantry_deg": 0.0, "gantry_direction": "CW"},
            {"meterset_weight": 0.5, "gantry_deg": 10.0}, {"meterset_weight": 1.0,
                                                           "gantry_deg": 20.0}]}]})
    path = write_rt_plan(plan, tmp_path / "p.dcm")
    ds = pydicom.dcmread(path)
    ds.BeamSequence[0].ControlPointSequence[0].DoseRateSet = 300.0
    ds.save_as(path)
    rates = rt_plan_dose_rates(path)
    assert rates == {"ARC": [300.0, 300.0, 300.0]}
    tl = delivery_timeline(Plan.from_rt_plan(path).treatment_beams, rates)
    np.testing.assert_allclose(np.diff(tl.beams[0].times_s), [20.0, 20.0])  # 100 MU, 5 MU/s


def test_machine_keys_are_checked():
    bad = {"type": "linac", "spectrum": "6MV", "isocenter_mm": [0.0, 0.0, 0.0],
           "max_gantry_deg_per_s": 0.0}
    with pytest.raises(PlanError, match="max_gantry_deg_per_s = 0.0 must be a positive"):
        Plan.from_dict({"beam": [bad]})


def test_regular_cycle_phases_and_start():
    s, i = regular_cycle(4.0, 33.0, PCT, 10.0)
    assert i[0] == 3 and s[1] == pytest.approx((35.0 - 33.0) / 100.0 * 4.0)
    assert list(i[:12]) == [3, 4, 5, 6, 7, 8, 9, 0, 1, 2, 3, 4]
    np.testing.assert_allclose(np.diff(s[1:-1]), 0.4)  # 10 % of 4 s each


def test_a_trace_in_one_phase_sends_every_mu_there():
    plan = vmat()
    tl = delivery_timeline(plan.treatment_beams)
    trace = BreathingTrace(np.array([0.0, 1000.0]), np.array([42.0, 38.0]), "phase_percent")
    s, i = trace.intervals(PCT)
    d = split_by_phase(tl, s, i, len(PCT), t0_s=3.0)
    assert d.mu[4] == pytest.approx(500.0) and np.sum(d.mu) == d.mu[4]
    w = d.source_weights(plan)
    assert w[4] == pytest.approx(sum(x.weight for x in plan.sources), rel=1e-12)
    pieces = d.plan(4, plan).sources
    assert len(pieces) == len(plan.sources)  # the same intervals, uncut
    for a, b in zip(pieces, plan.sources, strict=True):
        assert a.weight == pytest.approx(b.weight, rel=1e-12)
        for t in (0.0, 0.3, 1.0):
            np.testing.assert_allclose(a.angles_at(t), b.angles_at(t), atol=1e-9)
            np.testing.assert_allclose(a.aperture_at(t), b.aperture_at(t), atol=1e-9)


def test_pieces_partition_the_plan():
    """Cut by a random cycle, the phases' pieces add up to the plan: MU, photons (weights),
    gantry turns, and each piece's machine is the plan's at the same instant."""
    plan = vmat()
    tl = delivery_timeline(plan.treatment_beams)
    s, i = regular_cycle(3.7, 61.0, PCT, tl.end_s)
    d = split_by_phase(tl, s, i, len(PCT))
    assert np.sum(d.mu) == pytest.approx(500.0, rel=1e-12)
    assert np.sum(d.source_weights(plan)) == pytest.approx(
        sum(x.weight for x in plan.sources), rel=1e-12)
    turns = sum(abs(x.turns_deg[0]) for p in range(10) for x in d.plan(p, plan).sources
                if isinstance(x, DynamicSegment))
    assert turns == pytest.approx(179.0 + 179.0 + 358.0)
    seg = plan.sources[0]  # A1 181° → 0°, 150 MU over 29.83 s
    first = d.plan(int(i[0]), plan).sources[0]  # delivered from t = 0 in the start phase
    t_end = s[1]
    u = t_end / tl.beams[0].times_s[1]
    np.testing.assert_allclose(first.angles_at(1.0), seg.angles_at(u), atol=1e-9)
    np.testing.assert_allclose(first.aperture_at(0.5), seg.aperture_at(0.5 * u), atol=1e-9)
    assert first.meterset == pytest.approx(150.0 * u)


def test_fast_cycle_gives_each_phase_its_time_share():
    plan = vmat()
    tl = delivery_timeline(plan.treatment_beams)
    s, i = regular_cycle(1.0, 0.0, PCT, tl.end_s)  # 120 cycles over 120 s
    d = split_by_phase(tl, s, i, len(PCT))
    # a phase's share differs from 1/10 by at most one partial visit per control-point
    # interval: 3 intervals × 0.1 s × ≤ 5.03 MU/s
    assert np.max(np.abs(d.mu - 50.0)) < 3 * 0.1 * 5.1
    w = d.source_weights(plan)
    np.testing.assert_allclose(w / w.sum(), 0.1, atol=0.004)


def test_random_starts_converge_to_the_time_share():
    """The mean MU share over random start phases → 1/K; its error shrinks like 1/√N."""
    tl = delivery_timeline(vmat().treatment_beams)
    rng = np.random.default_rng(5)
    shares = []
    for start in rng.uniform(0.0, 100.0, 24):
        s, i = regular_cycle(4.0, start, PCT, tl.end_s)
        shares.append(split_by_phase(tl, s, i, len(PCT)).mu / 500.0)
    shares = np.array(shares)
    err = [np.max(np.abs(shares[:n].mean(0) - 0.1)) for n in (3, 24)]
    sd_one = shares.std(0).max()
    assert sd_one > 1e-3  # one 120 s delivery over a 4 s cycle: not exactly the time share
    assert err[1] < 4 * sd_one / np.sqrt(24) and err[1] < err[0]


def test_amplitude_trace_follows_the_branches():
    """A cos² trace over two cycles visits the phases 0 → 9 in order, twice (the rising and
    falling branches of equal amplitude told apart), each starting near its own time."""
    t = np.linspace(0.0, 8.0, 801)
    amp = 10.0 * np.cos(np.pi * t / 4.0) ** 2  # period 4 s, 10 mm at t = 0 (phase 0)
    pa = 10.0 * np.cos(np.pi * PCT / 100.0) ** 2
    idx = amplitude_phase(amp, pa)
    keep = np.r_[True, idx[1:] != idx[:-1]]
    np.testing.assert_array_equal(idx[keep], [*range(10), *range(10), 0])
    centre = (t[keep][:-1] + np.r_[t[keep][1:-1], 8.0]) / 2.0  # mid-visit time
    assert np.all(np.abs(centre % 4.0 - np.r_[PCT, PCT] / 25.0) < 0.45)


def test_trace_files_are_read_and_checked(tmp_path):
    f = tmp_path / "t.csv"
    f.write_text("time_s, phase_percent\n0, 0\n1, 25\n2, 50\n")
    tr = BreathingTrace.read(f)
    s, i = tr.intervals([0.0, 50.0])
    np.testing.assert_allclose(s, [0.0, 1.5]) and np.testing.assert_array_equal(i, [0, 1])
    f.write_text("time_s,breath\n0,1\n")
    with pytest.raises(OptionError, match="header must name time_s"):
        BreathingTrace.read(f)
    f.write_text("time_s,phase_percent\n0,0\n0,5\n")
    with pytest.raises(OptionError, match="must increase"):
        BreathingTrace.read(f)
    with pytest.raises(OptionError, match="--phase-amplitudes-mm"):
        BreathingTrace(np.array([0.0, 1.0]), np.array([1.0, 2.0]), "amplitude_mm").intervals(PCT)
