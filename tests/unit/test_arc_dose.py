"""Dose of moving deliveries, small and fast (water cylinder, 5 mm voxels, 2·10⁵ photons): an arc
equals the sum of its static beams, the same arc backwards gives the same dose, the other half
circle the mirrored dose, and a sliding-window sweep equals step-and-shoot of its interpolated
apertures (issue 22). The full-size versions with γ are in tests/verification/test_arc_dose.py."""

import pytest

from arc_dose import compare, dose, linac, sliding_window, statics, water_cylinder

N = 200_000
JAWS = [-20, 20, -10, 10]


@pytest.fixture(scope="module")
def geometry():
    return water_cylinder()


@pytest.fixture(scope="module")
def arc_cw(geometry):
    return dose([linac(arc={"start_deg": 0, "stop_deg": 180, "direction": "CW"}, jaws_mm=JAWS,
                       weight=100)], N, 1, geometry)


def _agree(a, b):
    within, z2, n = compare(a, b)
    assert n > 1000
    assert within >= 0.985 and z2 < 1.3, (within, z2)


def test_arc_equals_the_sum_of_its_static_beams(geometry, arc_cw):
    """0° → 180° CW against 91 static beams at 2° steps with the same meterset (trapezoidal
    weights, see arc_dose.statics)."""
    _agree(arc_cw, dose(statics(0, 180, 2, 100, jaws_mm=JAWS), N, 2, geometry))


def test_arc_backwards_is_the_same_arc_and_the_other_direction_the_other_half(geometry, arc_cw):
    back = dose([linac(arc={"start_deg": 180, "stop_deg": 0, "direction": "CC"}, jaws_mm=JAWS,
                       weight=100)], N, 3, geometry)
    _agree(arc_cw, back)
    other = dose([linac(arc={"start_deg": 180, "stop_deg": 0, "direction": "CW"}, jaws_mm=JAWS,
                        weight=100)], N, 4, geometry)
    assert compare(arc_cw, other)[1] > 20  # not the same half …
    mirrored = (arc_cw[0][..., ::-1], arc_cw[1][..., ::-1])  # … but its mirror image in x
    _agree(mirrored, other)


def test_sliding_window_equals_step_and_shoot_of_its_interpolated_apertures(geometry):
    sweep = dose(sliding_window(), N, 5, geometry)
    _agree(sweep, dose(sliding_window(70), N, 6, geometry))
    assert compare(sweep, dose(sliding_window(7), N, 7, geometry))[1] > 1.4  # the test can fail
