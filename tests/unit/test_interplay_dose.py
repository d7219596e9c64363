"""Interplay dose (issue 31) through transport, kept tiny: a trace in one phase gives that
phase's dose, a fast cycle the time-weighted 4D dose (both within statistics, independent random
streams), and the CLI's one fraction and fraction course with their records and refusals."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from tetdose.cli import main
from tetdose.dose.dose4d import run_dose4d
from tetdose.dose.interplay import run_interplay
from tetdose.motion import BreathingModel, update_series
from tetdose.motion.trace import regular_cycle
from tetdose.plan.delivery import delivery_timeline
from tetdose.transport import Plan, TransportSettings

from helpers import box_mesh

ARC = ('[[beam]]\ntype = "linac"\nspectrum = "6MV"\nisocenter_mm = [20.0, 20.0, 20.0]\n'
       'jaws_mm = [-12.0, 12.0, -12.0, 12.0]\nweight = 100.0\n'
       'arc = { start_deg = 0.0, stop_deg = 180.0, direction = "CW" }\n'
       '[regions]\ntumour = 2\n')
SETTINGS = TransportSettings(12000, 10, 7, physics="kerma")
#: Bounds of the mean z² of two independent runs: batch σ with 9 degrees of freedom give
#: E[z²] ≈ 9/7 (Student t); a phase's dose against another phase's gives z² ≈ 120.
Z2 = (0.6, 2.0)


def series(n_phases: int = 3):
    ref = box_mesh([0, 0, 0], [40, 40, 40], (4, 4, 4), jitter=0.15, seed=3)
    c = ref.centroids_mm
    ref = replace(ref, region=np.where(np.linalg.norm(c - 20.0, axis=1) < 12.0, 2, 1))
    s = BreathingModel(amplitude_mm=8.0).series(ref, n_phases)
    return update_series(s, np.full(ref.n_points, 1.0))[0]


def mean_z2(a, sa, b, sb):
    ok = (sa > 0) & (sb > 0) & (a > 0.2 * a.max())
    z = (a - b)[ok] / np.hypot(sa, sb)[ok]
    return float(np.mean(z**2)), int(ok.sum())


@pytest.fixture(scope="module")
def setup():
    s = series()
    plan = Plan.from_dict({"beam": [{"type": "linac", "spectrum": "6MV", "weight": 100.0,
                                     "isocenter_mm": [20.0, 20.0, 20.0],
                                     "jaws_mm": [-12.0, 12.0, -12.0, 12.0],
                                     "arc": {"start_deg": 0.0, "stop_deg": 180.0,
                                             "direction": "CW"}}]})
    return s, plan, run_dose4d(s, plan, SETTINGS), delivery_timeline(plan.treatment_beams)


def test_a_trace_in_one_phase_gives_that_phases_dose(setup):
    s, plan, tw, tl = setup
    starts, idx = np.array([0.0]), np.array([2])  # the patient stays in phase 2
    one = run_interplay(s, plan, SETTINGS, tl, starts, idx)
    assert one.delivery["mu_per_phase"] == pytest.approx([0.0, 0.0, 100.0])
    assert one.series.n_phases == 1 and one.results[0].n_histories == 3 * SETTINGS.n_histories
    ref = tw.results[2].mesh_part()
    z2, n = mean_z2(one.accumulated.dose_gy, one.accumulated.dose_std_gy, ref.dose_gy,
                    ref.dose_std_gy)
    assert n > 50 and Z2[0] < z2 < Z2[1]


def test_a_fast_cycle_gives_the_time_weighted_dose(setup):
    s, plan, tw, tl = setup
    starts, idx = regular_cycle(0.3, 0.0, s.phase_percent, tl.end_s)
    fast = run_interplay(s, plan, SETTINGS, tl, starts, idx)
    np.testing.assert_allclose(fast.accumulated.weights, 1 / 3, atol=0.01)
    a, b = fast.accumulated, tw.accumulated
    z2, n = mean_z2(a.dose_gy, a.dose_std_gy, b.dose_gy, b.dose_std_gy)
    assert n > 50 and Z2[0] < z2 < Z2[1]


def test_cli_fraction_and_course(tmp_path, capsys):
    series(2).write(tmp_path / "phases")
    (tmp_path / "plan.toml").write_text(ARC)
    common = ["dose4d", "--physics", "kerma", "-q", "--phases", str(tmp_path / "phases"),
              "--plan", str(tmp_path / "plan.toml"), "--histories", "2000", "--batches", "4"]
    assert main([*common, "--breathing-period-s", "4", "--start-phase", "30",
                 "-o", str(tmp_path / "one")]) == 0
    d = json.loads((tmp_path / "one" / "summary.json").read_text())["delivery"]
    assert sum(d["mu_per_phase"]) == pytest.approx(100.0)
    assert d["delivery_s"] == pytest.approx(30.0) and d["trace"]["start_phase_percent"] == 30.0
    assert main([*common, "--breathing-period-s", "4", "--start-phase", "random",
                 "--fractions", "3", "--target", "tumour", "--static-phase", "50",
                 "-o", str(tmp_path / "course")]) == 0
    out = capsys.readouterr().out
    assert "static 50 %" in out and "n=2" in out
    rep = json.loads((tmp_path / "course" / "summary.json").read_text())
    r = rep["interplay"]
    assert r["static_phase_percent"] == 50.0
    assert len(r["per_fraction"]) == 3
    assert len({t["start_phase_percent"] for t in rep["starts"]}) == 3
    assert r["fraction_mean"]["mean"] == pytest.approx(np.mean([p["mean"] for p in
                                                                r["per_fraction"]]))
    for f in (1, 2, 3):
        mu = json.loads((tmp_path / "course" / f"fraction_{f:03d}" / "summary.json").read_text(
            ))["delivery"]["mu_per_phase"]
        assert sum(mu) == pytest.approx(100.0)
    assert (tmp_path / "course" / "time_weighted" / "accumulated.vtu").exists()


@pytest.mark.parametrize("extra, message", [
    (["--target", "tumour"], "belongs to the delivery in time"),
    (["--breathing-period-s", "4", "--fractions", "3"], "--start-phase random --target"),
    (["--breathing-period-s", "4", "--breathing-trace", "t.csv"], "not both"),
])
def test_cli_refusals(tmp_path, capsys, extra, message):
    series(2).write(tmp_path / "phases")
    (tmp_path / "plan.toml").write_text(ARC)
    assert main(["dose4d", "--phases", str(tmp_path / "phases"), "--plan",
                 str(tmp_path / "plan.toml"), *extra, "-o", str(tmp_path / "o")]) == 2
    assert message in capsys.readouterr().err


def test_cli_refuses_a_prescription(tmp_path, capsys):
    series(2).write(tmp_path / "phases")
    (tmp_path / "plan.toml").write_text(ARC + '[prescription]\nstructure = "tumour"\n'
                                        'dose_gy = 2.0\n')
    assert main(["dose4d", "--phases", str(tmp_path / "phases"), "--plan",
                 str(tmp_path / "plan.toml"), "--breathing-period-s", "4",
                 "-o", str(tmp_path / "o")]) == 2
    assert "hides the interplay" in capsys.readouterr().err


@pytest.mark.slow  # 38 s at load 15 (ompmc start-up per phase, the virtual phase CTs)
def test_interplay_with_ompmc_on_the_phase_cts(setup):
    """--engine ompmc: each phase's share through ompmc on its body CT (tetdose's sampler of
    the cut arc): a trace in phase 1 sends it every MU, and the fraction is that phase's run."""
    pytest.importorskip("ompmc", reason="ompmc (tetdose[ompmc]) is not installed")
    from tetdose.core.image import Image
    from tetdose.coupling.ompmc import OmpmcOptions, phase_engine

    from helpers import grid_for

    s, plan, _tw, tl = setup
    grid = grid_for([-10, -10, -10], [50, 50, 50], [5, 5, 5])
    ct = Image(np.full(grid.shape, -700, dtype=np.int16), grid)
    run = run_interplay(s, plan, TransportSettings(2000, 4, 3), tl, np.array([0.0]),
                        np.array([1]), ct_hu=ct,
                        voxel_engine=phase_engine(OmpmcOptions(electron_cutoff_mev=15.0)))
    assert run.delivery["mu_per_phase"] == pytest.approx([0.0, 100.0, 0.0])
    assert [r.extra["engine"] for r in run.results] == ["ompmc"]
    assert run.results[0].n_histories == 3 * 2000
    np.testing.assert_allclose(run.accumulated.dose_gy, run.results[0].dose_gy, rtol=1e-12)
    assert run.accumulated.dose_gy.max() > 0


def test_a_structure_isocentre_is_resolved_before_the_cut(setup):
    s, _plan, _tw, _tl = setup
    plan = Plan.from_dict({"beam": [{"type": "linac", "spectrum": "6MV", "weight": 10.0,
                                     "isocenter": "tumour", "arc": {
                                         "start_deg": 0.0, "stop_deg": 90.0,
                                         "direction": "CW"}}], "regions": {"tumour": 2}})
    from tetdose.dose.interplay import check_interplay_plan
    from tetdose.plan.phase_split import split_by_phase

    check_interplay_plan(plan)
    resolved = plan.resolved(s.reference)
    tl = delivery_timeline(plan.treatment_beams).with_beams(resolved.treatment_beams)
    d = split_by_phase(tl, np.array([0.0]), np.array([0]), 3)
    np.testing.assert_allclose(d.beams[0][0].isocenter_mm, resolved.treatment_beams[0].isocenter_mm)
    assert np.linalg.norm(d.beams[0][0].isocenter_mm - 20.0) < 3.0  # the tumour's centroid
