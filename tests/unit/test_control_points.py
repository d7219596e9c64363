"""Control points: rotation directions through 0/360 (DICOM C.8.8.14.8), the exact open area of an
interpolated aperture, plan.toml control_points/arc, and the source kernel's continuous sampling of
a moving delivery checked photon by photon against the Python state of the machine at the
photon's meterset fraction (recovered from where the photon starts)."""

import numpy as np
import pytest
from scipy.optimize import minimize_scalar

from tetdose._random import seed_for
from tetdose.errors import PlanError
from tetdose.plan import Plan
from tetdose.plan.beams import (
    MLC,
    ControlPoint,
    LinacBeam,
    aperture_rectangles,
    beam_axes,
    rotation_deg,
)
from tetdose.plan.segments import DynamicSegment, area_mean_and_max, beam_sources, open_area_mm2
from tetdose.transport.run.settings import TransportSettings
from tetdose.transport.sources._sample import sample_source
from tetdose.transport.sources.arrays import source_arrays

SETTINGS = TransportSettings(n_histories=10, n_batches=2, physics="kerma")


@pytest.mark.parametrize(("a", "b", "direction", "sense", "turn"), [
    (350, 10, "CW", 1, 20),      # through 0: 20°, not 340°
    (10, 350, "CC", 1, -20),
    (350, 10, "CC", 1, -340),
    (0, 180, "CW", 1, 180),
    (180, 0, "CC", 1, -180),     # the same half circle, backwards
    (180, 0, "CW", 1, 180),      # the other half
    (5, 5, "CW", 1, 360),        # DICOM example 2: a full turn
    (5, 5, "NONE", 1, 0),        # example 1: no movement
    (170, 160, "CC", -1, 350),   # example 3: the couch angle grows counter-clockwise
    (170, 160, "CW", -1, -10),
    (350, 10, "NONE", 1, 20),    # NONE with a change: the shorter turn
])
def test_rotation_follows_the_direction_through_zero(a, b, direction, sense, turn):
    assert rotation_deg(a, b, direction, sense) == pytest.approx(turn)


def test_rotation_without_direction_by_half_a_turn_is_refused():
    with pytest.raises(PlanError, match="ambiguous"):
        rotation_deg(0, 180, "NONE")
    with pytest.raises(PlanError, match="unknown"):
        rotation_deg(0, 10, "CCW")


def _random_cp(rng, weight, axis="X"):
    bnd = np.array([-30.0, -20.0, -5.0, 0.0, 12.0, 30.0])
    lo = rng.uniform(-40, 20, 5)
    mlc = MLC(bnd, np.concatenate([lo, lo + rng.uniform(0, 30, 5)]), axis)
    jaws = [rng.uniform(-35, -5), rng.uniform(5, 35), rng.uniform(-35, -5), rng.uniform(5, 35)]
    return ControlPoint(jaws_mm=jaws, mlc=mlc, meterset_weight=weight)


@pytest.mark.parametrize("axis", ["X", "Y"])
def test_mean_and_max_open_area_are_exact(axis):
    """Ā and A_max of an aperture whose leaves cross jaws, boundaries and each other on the way,
    against a dense sampling of A(t) (and A(t) against the rectangles of aperture_rectangles)."""
    rng = np.random.default_rng(4)
    t = np.linspace(0.0, 1.0, 200_001)
    for _ in range(5):
        a, b = _random_cp(rng, 0.0, axis), _random_cp(rng, 1.0, axis)
        area = open_area_mm2(a, b, t)
        mean, peak = area_mean_and_max(a, b)
        assert mean == pytest.approx(np.trapezoid(area, t), rel=1e-6, abs=1e-6)
        # The grid misses a kink's peak by at most |dA/dt|·Δt ≈ 1e4 mm² · 5e-6 = 0.05 mm².
        assert peak >= area.max() - 1e-9 and peak == pytest.approx(area.max(), abs=0.05)
        seg_mid = aperture_rectangles(a.jaws_mm + 0.3 * (b.jaws_mm - a.jaws_mm),
                                      a.mlc.moved(0.7 * a.mlc.positions_mm
                                                  + 0.3 * b.mlc.positions_mm))
        r = seg_mid
        assert open_area_mm2(a, b, [0.3])[0] == pytest.approx(
            np.sum((r[:, 1] - r[:, 0]) * (r[:, 3] - r[:, 2])))


def _beam(cps, pos="HFS", iso=(0.0, 0.0, 0.0), meterset=1.0):
    return LinacBeam("B", "Co60", iso, tuple(cps), 1000.0, pos, meterset)


def _samples(sources, n, seed=5):
    src = source_arrays(_PlanOf(sources), SETTINGS)
    return np.array([sample_source(src, np.uint64(seed_for(seed, 0, i)), np.empty(0))[2:] for i in range(n)])


class _PlanOf:
    """The minimal plan interface source_arrays reads: given sources."""

    def __init__(self, sources):
        self.sources = tuple(sources)

    def require_resolved(self):
        return None


def _recover_t(seg: DynamicSegment, start):
    """The meterset fraction t at which the source of ``seg`` sits at ``start``."""
    def miss(t):
        return np.linalg.norm(seg.isocenter_at(t) + seg.sad_mm * seg.axes_at(t)[2] - start)

    grid = np.linspace(0, 1, 401)
    t0 = grid[int(np.argmin([miss(t) for t in grid]))]
    res = minimize_scalar(miss, bounds=(max(t0 - 0.005, 0), min(t0 + 0.005, 1)),
                          method="bounded", options={"xatol": 1e-12})
    return res.x, res.fun


@pytest.mark.parametrize("pos", ["HFS", "HFP", "FFS", "FFP"])
def test_kernel_puts_the_machine_where_the_control_points_say(pos):
    """Gantry 100° → 140° CW with collimator 30° → 50°, couch 20° → 10° (CW: the couch angle
    falls), the isocentre moving and the leaves sliding: every photon starts at iso(t) +
    SAD·Z_b(t) for one t, and crosses the isocentre plane inside the aperture of that t."""
    bnd = [-20.0, -10.0, 0.0, 10.0, 20.0]
    a = ControlPoint(100, 30, 20, (-25, 25, -15, 15), MLC(bnd, [-20, -10, -5, 0, -5, 5, 10, 15]),
                     0.0, "CW", "CW", "CW", (5.0, -3.0, 2.0))
    b = ControlPoint(140, 50, 10, (-20, 30, -15, 18), MLC(bnd, [-5, 0, 5, 10, 10, 20, 20, 25]),
                     2.0, isocenter_mm=(8.0, -1.0, 2.0))
    (seg,) = beam_sources(_beam([a, b], pos))
    assert isinstance(seg, DynamicSegment) and seg.turns_deg == (40.0, 20.0, -10.0)
    out = _samples([seg], 400)
    ts = []
    for p, d in zip(out[:, :3], out[:, 3:], strict=True):
        t, miss = _recover_t(seg, p)
        assert miss < 1e-4  # mm: t is found to ~1e-9 (a 40° turn at SAD 1 m: 0.7 µm)
        ax, iso = seg.axes_at(t), seg.isocenter_at(t)
        hit = p + seg.sad_mm / np.dot(d, -ax[2]) * d - iso
        a1, a2 = hit @ ax[0], hit @ ax[1]
        r = seg.aperture_at(t)
        assert np.any((r[:, 0] - 1e-4 <= a1) & (a1 <= r[:, 1] + 1e-4)
                      & (r[:, 2] - 1e-4 <= a2) & (a2 <= r[:, 3] + 1e-4))
        ts.append(t)
    assert min(ts) < 0.05 and max(ts) > 0.95


def test_meterset_fraction_is_drawn_in_proportion_to_the_open_area():
    """A leaf pair opening from 0 to 20 mm while the gantry turns 0° → 10°: the open area grows
    as t, so photons come with density 2t (mean 2/3, P(t < ½) = ¼)."""
    bnd = [-10.0, 10.0]
    a = ControlPoint(0, 0, 0, (-50, 50, -50, 50), MLC(bnd, [0.0, 0.0]), 0.0, "CW")
    b = ControlPoint(10, 0, 0, (-50, 50, -50, 50), MLC(bnd, [0.0, 20.0]), 1.0)
    (seg,) = beam_sources(_beam([a, b]))
    assert seg.mean_area_mm2 == pytest.approx(200.0) and seg.max_area_mm2 == pytest.approx(400.0)
    out = _samples([seg], 4000)
    g = np.degrees(np.arctan2(out[:, 0], -out[:, 1]))  # HFS: source at (sin g, −cos g)·SAD
    t = g / 10.0
    n = len(t)
    assert abs(t.mean() - 2 / 3) < 4 * np.sqrt(1 / 18 / n)
    assert abs(np.mean(t < 0.5) - 0.25) < 4 * np.sqrt(0.25 * 0.75 / n)


def test_arc_through_zero_covers_twenty_degrees_uniformly():
    plan = Plan.from_dict({"beam": [{"type": "linac", "spectrum": "Co60", "isocenter_mm": [0, 0, 0],
                                     "arc": {"start_deg": 350, "stop_deg": 10, "direction": "CW"},
                                     "jaws_mm": [-20, 20, -10, 10]}]})
    out = _samples(plan.sources, 4000)
    g = np.degrees(np.arctan2(out[:, 0], -out[:, 1]))
    assert g.min() > -10 - 1e-9 and g.max() < 10 + 1e-9
    counts, _ = np.histogram(g, bins=4, range=(-10, 10))
    assert np.all(np.abs(counts - 1000) < 4 * np.sqrt(1000 * 0.75))
    long_way = Plan.from_dict({"beam": [{"type": "linac", "spectrum": "Co60",
                                         "isocenter_mm": [0, 0, 0], "arc": {
                                             "start_deg": 350, "stop_deg": 10, "direction": "CC"}}]})
    out = _samples(long_way.sources, 4000)
    g = np.degrees(np.arctan2(out[:, 0], -out[:, 1])) % 360.0  # 350 → 10 the long way: 340°
    assert g.min() > 10 - 1e-9 and g.max() < 350 + 1e-9
    counts, _ = np.histogram(g, bins=4, range=(10, 350))
    assert np.all(np.abs(counts - 1000) < 4 * np.sqrt(1000 * 0.75))


def test_a_static_field_keeps_the_static_source_and_a_still_interval_is_static():
    """One control point, or two with the same state, is the static point source of old; a
    step-and-shoot beam (segments with ΔW = 0 between them) gives one static source per segment
    with its share of the meterset."""
    cp = ControlPoint(30, 10, 0, (-30, 30, -20, 20))
    (one,) = beam_sources(_beam([cp], meterset=2.0))
    (two,) = beam_sources(_beam([ControlPoint(30, 10, 0, (-30, 30, -20, 20), None, 0.0),
                                 ControlPoint(30, 10, 0, (-30, 30, -20, 20), None, 5.0)],
                                meterset=2.0))
    assert one.kind == two.kind == "linac" and one.weight == two.weight
    np.testing.assert_array_equal(one.position_mm, two.position_mm)
    bnd = [-10.0, 0.0, 10.0]
    seg = [(MLC(bnd, [-5, -5, 5, 5]), 0.0), (MLC(bnd, [-5, -5, 5, 5]), 0.4),
           (MLC(bnd, [-9, 0, 0, 9]), 0.4), (MLC(bnd, [-9, 0, 0, 9]), 1.0)]
    srcs = beam_sources(_beam([ControlPoint(0, 0, 0, (-20, 20, -20, 20), m, w) for m, w in seg],
                              meterset=10.0))
    assert [s.kind for s in srcs] == ["linac", "linac"]
    # 4 MU through 200 mm², 6 MU through 180 mm² (relative to 100 × 100 mm²).
    assert [s.weight for s in srcs] == pytest.approx([4 * 200 / 1e4, 6 * 180 / 1e4])


def test_plan_toml_control_points_carry_forward_and_arc_shorthand():
    mlc = {"boundaries_mm": [-10, 0, 10], "positions_mm": [-5, -5, 5, 5]}
    plan = Plan.from_dict({"beam": [{
        "type": "linac", "spectrum": "6MV", "isocenter_mm": [1, 2, 3], "collimator_deg": 15,
        "jaws_mm": [-20, 20, -10, 10], "mlc": mlc, "control_points": [
            {"meterset_weight": 0, "gantry_deg": 181, "gantry_direction": "CW"},
            {"meterset_weight": 0.5, "gantry_deg": 270, "mlc": [-8, -2, 2, 8]},
            {"meterset_weight": 1, "gantry_deg": 179, "jaws_mm": [-15, 15, -10, 10]}]}]})
    cps = plan.treatment_beams[0].control_points
    assert [c.gantry_deg for c in cps] == [181, 270, 179]
    assert [c.gantry_rotation for c in cps] == ["CW"] * 3
    assert [c.collimator_deg for c in cps] == [15] * 3
    np.testing.assert_array_equal(cps[2].mlc.positions_mm, [-8, -2, 2, 8])
    np.testing.assert_array_equal(cps[1].jaws_mm, [-20, 20, -10, 10])
    assert [s.turns_deg[0] for s in plan.sources] == pytest.approx([89.0, 269.0])
    full = Plan.from_dict({"beam": [{"type": "linac", "spectrum": "6MV", "isocenter_mm": [0, 0, 0],
                                     "arc": {"start_deg": 180, "stop_deg": 180,
                                             "direction": "CC"}}]})
    assert full.sources[0].turns_deg == (-360.0, 0.0, 0.0)


def test_plan_toml_angle_omitted_after_a_direction_does_not_turn():
    """A gantry/collimator/couch direction given at control point 0 with later control points
    that do not name the angle: the angle is unchanged (no turn), as in DICOM."""
    mlc = {"boundaries_mm": [-10, 0, 10], "positions_mm": [-5, -5, 5, 5]}
    plan = Plan.from_dict({"beam": [{
        "type": "linac", "spectrum": "6MV", "isocenter_mm": [0, 0, 0], "gantry_deg": 40,
        "collimator_deg": 10, "couch_deg": 350, "mlc": mlc, "control_points": [
            {"meterset_weight": 0, "gantry_direction": "CW", "collimator_direction": "CC",
             "couch_direction": "CW"},
            {"meterset_weight": 0.5, "mlc": [0, 0, 8, 8]},
            {"meterset_weight": 1, "mlc": [5, 5, 9, 9], "gantry_deg": 60}]}]})
    assert [s.turns_deg for s in plan.sources] == [(0.0, 0.0, 0.0), (20.0, 0.0, 0.0)]


@pytest.mark.parametrize(("beam", "message"), [
    ({"sad_mm": 10}, "sad_mm = 10 mm is below 500 mm"),  # refused in an RT Plan too
    ({"control_points": [{"meterset_weight": 0, "gantry_direction": "CW"},
                         {"meterset_weight": 0.5, "gantry_deg": 0},
                         {"meterset_weight": 1, "gantry_deg": 0}]}, "through 720° one way"),
    ({"arc": {"start_deg": 0, "stop_deg": 90, "direction": "CW"}, "gantry_deg": 0}, "arc"),
    ({"arc": {"start_deg": 0, "stop_deg": 90}}, "direction"),
    ({"arc": {"start_deg": 0, "stop_deg": 90, "direction": "NONE"}}, "CW"),
    ({"control_points": [{"gantry_deg": 0}]}, "meterset_weight"),
    ({"control_points": [{"meterset_weight": 0, "mlc": [0, 1]}]}, "no mlc"),
    ({"control_points": [{"meterset_weight": 0, "gantry_dir": "CW"}]}, "unknown key"),
    ({"control_points": [{"meterset_weight": 1}, {"meterset_weight": 0}]}, "cumulative"),
    ({"control_points": [{"meterset_weight": 1}, {"meterset_weight": 1}]}, "no meterset"),
    ({"control_points": [{"meterset_weight": 0, "gantry_direction": "CCW"}]}, "unknown"),
    ({"control_points": []}, "non-empty"),
])
def test_plan_toml_control_point_errors_name_the_problem(beam, message):
    with pytest.raises(PlanError, match=message):
        Plan.from_dict({"beam": [{"type": "linac", "spectrum": "6MV", "isocenter_mm": [0, 0, 0],
                                  **beam}]})


def test_kernel_axes_match_beam_axes_through_the_grid_frame():
    """A rigid frame (a rotated, shifted grid) moves the dynamic source exactly as it moves the
    points and directions of beam_axes."""
    a = ControlPoint(10, 20, 30, (-5, 5, -5, 5), None, 0.0, "CW", "CC", "CC")
    b = ControlPoint(50, 0, 60, (-5, 5, -5, 5), None, 1.0)
    plan = Plan(treatment_beams=(_beam([a, b], "FFS", iso=(3.0, 4.0, 5.0)),))
    q, _ = np.linalg.qr(np.random.default_rng(1).normal(size=(3, 3)))
    shift = np.array([7.0, -2.0, 11.0])

    def to_frame(x, is_dir):
        return x @ q if is_dir else (x - shift) @ q

    src = source_arrays(plan, SETTINGS, to_frame)
    seg = plan.sources[0]
    for i in range(200):
        p = sample_source(src, np.uint64(seed_for(2, 0, i)), np.empty(0))[2:5]
        patient = np.asarray(p) @ q.T + shift
        t, miss = _recover_t(seg, patient)
        assert miss < 1e-4  # mm: t is found to ~1e-9 (a 40° turn at SAD 1 m: 0.7 µm)
        ax = beam_axes(*seg.angles_at(t), "FFS")
        np.testing.assert_allclose(patient, seg.isocenter_at(t) + 1000 * ax[2], atol=1e-6)
