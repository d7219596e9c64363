"""plan.toml parsing, beam and settings validation (PlanError with a useful message)."""

from __future__ import annotations

import textwrap

import numpy as np
import pytest

from tetdose.errors import PlanError
from tetdose.transport import PhotonSource, Plan, TransportSettings

PLAN = """
[[beam]]
type = "point"
energy_mev = 1.0
position_mm = [0.0, 0.0, 0.0]
direction = [0.0, 0.0, 2.0]
half_angle_deg = 30.0
weight = 2.0

[[beam]]
type = "parallel"
spectrum = "spec.csv"
position_mm = [0.0, 0.0, -100.0]
direction = [0.0, 1.0, 1.0]
field_mm = [100.0, 50.0]

[materials]
1 = "water"
7 = "lung"

[normalization]
particles = 1e10
"""


def _write(tmp_path, text, spectrum="energy_mev,weight\n0.5,1\n2.0,3\n"):
    (tmp_path / "spec.csv").write_text(spectrum)
    path = tmp_path / "plan.toml"
    path.write_text(textwrap.dedent(text))
    return path


def test_plan_toml_is_parsed(tmp_path):
    plan = Plan.from_toml(_write(tmp_path, PLAN))
    point, parallel = plan.beams
    assert point.kind == "point" and point.half_angle_deg == 30.0 and point.weight == 2.0
    np.testing.assert_allclose(point.direction, [0, 0, 1])
    np.testing.assert_allclose(parallel.energies_mev, [0.5, 2.0])
    np.testing.assert_allclose(parallel.line_weights, [1, 3])
    assert parallel.mean_energy_mev == pytest.approx((0.5 + 6.0) / 4)
    assert plan.materials == {1: "water", 7: "lung"} and plan.particles == 1e10
    # field axes: orthonormal, perpendicular to the beam, right-handed (e1 × e2 = axis)
    for b in plan.beams:
        frame = np.array([b.e1, b.e2, b.direction])
        np.testing.assert_allclose(frame @ frame.T, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(np.cross(b.e1, b.e2), b.direction, atol=1e-12)


@pytest.mark.parametrize("edit, match", [
    (lambda t: t.replace('type = "point"', 'type = "laser"'), "unknown"),
    (lambda t: t.replace("energy_mev = 1.0", "energy_mev = 1.0\nspectrum = 'spec.csv'"),
     "exactly one of energy_mev or spectrum"),
    (lambda t: t.replace("energy_mev = 1.0", "energy_mev = -1.0"), "positive MeV"),
    (lambda t: t.replace("weight = 2.0", "weight = 0.0"), "weight must be positive"),
    (lambda t: t.replace("direction = [0.0, 0.0, 2.0]", "direction = [0.0, 0.0, 0.0]"),
     "zero vector"),
    (lambda t: t.replace("field_mm = [100.0, 50.0]", ""), "positive field_mm"),
    (lambda t: t.replace("half_angle_deg = 30.0", "half_angle_deg = 270.0"), r"\(0, 180\]"),
    (lambda t: t.replace("weight = 2.0", "wieght = 2.0"), "unknown key"),
    (lambda t: t.replace("1 = \"water\"", "one = \"water\""), "integer region labels"),
    (lambda t: t.replace("particles = 1e10", "particles = -1"), "particles must be positive"),
    (lambda t: t.replace("[normalization]", "[normalisation]"), "unknown plan section"),
    (lambda t: t.replace("[[beam]]", "[[beam]\n"), "not valid TOML"),
    (lambda t: "[materials]" + t.split("[materials]")[1], "at least one beam"),
])
def test_bad_plans_raise_plan_error(tmp_path, edit, match):
    with pytest.raises(PlanError, match=match):
        Plan.from_toml(_write(tmp_path, edit(PLAN)))


def test_bad_spectrum_and_missing_files(tmp_path):
    with pytest.raises(PlanError, match="energy_mev, weight"):
        Plan.from_toml(_write(tmp_path, PLAN, spectrum="e,w\n1,2\n"))
    with pytest.raises(PlanError, match="cannot read plan"):
        Plan.from_toml(tmp_path / "missing.toml")


@pytest.mark.parametrize("kwargs, match", [
    ({"n_histories": 5, "n_batches": 10}, "at least n_batches"),
    ({"n_histories": 100, "n_batches": 1}, "at least 2"),
    ({"n_histories": 100, "seed": -1}, "non-negative"),
    ({"n_histories": 100, "energy_cutoff_mev": 0.0}, "energy_cutoff_mev"),
    ({"n_histories": 100, "estimator": "collision"}, "estimator"),
])
def test_bad_settings_raise_plan_error(kwargs, match):
    with pytest.raises(PlanError, match=match):
        TransportSettings(**kwargs)


def test_tally_memory_cap():
    settings = TransportSettings(100, 10, max_tally_bytes=8 * 10 * 1000, physics="kerma")
    settings.check_tally_size(1000)
    with pytest.raises(PlanError, match="fewer batches"):
        settings.check_tally_size(1001)


def test_field_x_direction_must_not_be_the_axis():
    with pytest.raises(PlanError, match="parallel to the beam"):
        PhotonSource("parallel", [0, 0, 0], [0, 0, 1], field_mm=[1, 1],
                     field_x_direction=[0, 0, 3])
