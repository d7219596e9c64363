"""[calibration] gy_per_mu: equal fluence per MU for every aperture, the reference phantom, the
refusals, and the analytic consistency: a plan in the reference conditions gives gy_per_mu × MU
at the reference point (within the statistics of the two Monte Carlo runs)."""

import numpy as np
import pytest

from tetdose.dose.absolute import (
    absolute_result,
    calibration_scale,
    reference_dose_per_photon,
    run_physics,
)
from tetdose.errors import PlanError
from tetdose.plan.beams import aperture_rectangles, fluence_weight
from tetdose.plan.mu_calibration import MUCalibration, reference_phantom
from tetdose.transport import Plan, TransportSettings, simulate

N_REF = 800_000


def _linac(mu, jaws=(-50, 50, -50, 50), spectrum="Co60", **extra):
    return {"type": "linac", "spectrum": spectrum, "isocenter_mm": [0, 0, 0],
            "jaws_mm": list(jaws), "weight": mu, **extra}


def _cal(gy_per_mu=0.01, **extra):
    return {"gy_per_mu": gy_per_mu, "reference_histories": N_REF, **extra}


def test_fluence_weight_is_mu_times_solid_angle():
    ref = aperture_rectangles((-50, 50, -50, 50))
    assert fluence_weight(200.0, ref, 1000.0) == pytest.approx(200.0)
    # A quarter of the area: a quarter of the photons per MU, the same fluence per MU.
    assert fluence_weight(200.0, aperture_rectangles((-25, 25, -25, 25)), 1000.0) == \
        pytest.approx(50.0)
    # The same aperture on the isocentre plane at SAD 800 mm subtends (1000/800)² more.
    assert fluence_weight(1.0, ref, 800.0) == pytest.approx((1000 / 800) ** 2)
    plan = Plan.from_dict({"beam": [_linac(30.0, (-20, 20, -10, 30))]})
    assert plan.sources[0].weight == pytest.approx(30.0 * 40 * 40 / 100 / 100)


def test_reference_voxel_is_centred_on_the_axis_at_the_reference_depth():
    for depth in (100.0, 50.0, 15.0):
        rho, _lab, index = reference_phantom(depth)
        k, j, i = np.unravel_index(index, rho.grid.shape)
        centre = rho.grid.index_to_physical(np.array([[i, j, k]], dtype=np.float64))[0]
        np.testing.assert_allclose(centre, [0.0, depth, 0.0], atol=1e-9)
        assert rho.grid.spacing_mm[1] * rho.grid.shape[1] >= 300.0  # ≥ 300 mm of water


def test_refusals():
    with pytest.raises(PlanError, match="not both"):
        Plan.from_dict({"beam": [_linac(1.0)], "calibration": _cal(),
                        "prescription": {"structure": "1", "dose_gy": 2.0}})
    with pytest.raises(PlanError, match="gy_per_mu must be positive"):
        Plan.from_dict({"beam": [_linac(1.0)], "calibration": {"gy_per_mu": 0.0}})
    with pytest.raises(PlanError, match="needs gy_per_mu"):
        Plan.from_dict({"beam": [_linac(1.0)], "calibration": {"dose": 1.0}})
    simple = Plan.from_dict({"beam": [{"type": "pencil", "energy_mev": 1.0,
                                       "position_mm": [0, 0, 0]}], "calibration": _cal()})
    with pytest.raises(PlanError, match="linac beams only"):
        calibration_scale(simple)
    mixed = Plan.from_dict({"beam": [_linac(1.0), _linac(1.0, spectrum="6MV")],
                            "calibration": _cal()})
    with pytest.raises(PlanError, match="one beam quality"):
        calibration_scale(mixed)
    with pytest.raises(PlanError, match="build-up"):
        reference_dose_per_photon("6MV", MUCalibration(0.01, depth_mm=5.0), physics="kerma")


def test_reference_conditions_give_gy_per_mu_times_mu():
    """Co-60, 100 × 100 mm² at SSD 1000 mm, 200 MU split into two beams (150 + 50 MU) and,
    in the second plan, one beam whose aperture is two leaf-pair halves: at 100 mm depth the
    dose is 0.01 Gy/MU × 200 MU = 2 Gy, within 4 σ of the two independent runs."""
    rho, lab, index = reference_phantom(100.0)
    mlc = {"boundaries_mm": [-50, 0, 50], "positions_mm": [-50, -50, 50, 50]}
    plans = [[_linac(150.0), _linac(50.0)], [_linac(200.0, mlc=mlc)]]
    for k, beams in enumerate(plans):
        plan = Plan.from_dict({"beam": beams, "materials": {1: "water"}, "calibration": _cal()})
        r = simulate(rho, plan, TransportSettings(N_REF, 10, 7 + k, physics="kerma"), labels=lab,
                     progress=False)
        r = absolute_result(r, plan, rho, lab)
        rec = r.record()
        d, s = r.dose_gy[index], r.dose_std_gy[index]
        s_ref = rec["mu_calibration"]["reference_gy_per_photon_std"] / \
            rec["mu_calibration"]["reference_gy_per_photon"]
        sigma = 2.0 * np.hypot(s / d, s_ref)
        print(f"plan {k}: D(ref) = {d:.4f} Gy, expected 2 Gy ± {sigma:.4f}")
        assert abs(d - 2.0) < 4 * sigma
        assert sigma < 0.02 * 2.0  # the check is not swamped by noise
        assert rec["units"]["dose"] == "Gy per fraction"
        assert rec["mu_calibration"]["mu"] == pytest.approx(200.0)
        assert rec["calibration_scale"] == pytest.approx(
            0.01 * 200.0 / rec["mu_calibration"]["reference_gy_per_photon"])


def test_cli_dose_record_says_gy_per_fraction_and_keeps_the_calibration(tmp_path):
    """`tetdose dose --ct` with [calibration]: the record holds mu_calibration beside the HU
    curve's name (`calibration`), the unit is Gy per fraction, the image is scaled by it."""
    import json

    from tetdose.cli import main
    from tetdose.core.image import Image, ImageGrid
    from tetdose.core.io import read_image, write_image

    grid = ImageGrid(np.array([-45.0, 5.0, -45.0]), np.full(3, 10.0), np.eye(3), (10, 10, 10))
    write_image(tmp_path / "ct.nrrd", Image(np.zeros(grid.shape, dtype=np.int16), grid))
    (tmp_path / "plan.toml").write_text(
        '[[beam]]\ntype = "linac"\nspectrum = "Co60"\nisocenter_mm = [0, 0, 0]\nweight = 50.0\n'
        '[calibration]\ngy_per_mu = 0.01\nreference_histories = 20000\n')
    assert main(["dose", "--physics", "kerma",
                 "--ct", str(tmp_path / "ct.nrrd"), "--plan", str(tmp_path / "plan.toml"),
                 "--histories", "5e3", "-q", "-o", str(tmp_path / "dose.nrrd")]) == 0
    rec = json.loads((tmp_path / "dose.json").read_text())
    assert rec["units"]["dose"] == "Gy per fraction"
    assert rec["calibration"] == "schneider2000"  # the HU curve, untouched
    cal = rec["mu_calibration"]
    assert cal["gy_per_mu"] == 0.01 and cal["mu"] == 50.0
    assert rec["calibration_scale"] == pytest.approx(0.5 / cal["reference_gy_per_photon"])
    dose = read_image(tmp_path / "dose.nrrd").array
    assert 0.1 < dose.max() < 2.0  # ~0.5 Gy at 100 mm, more at d_max: Gy, not Gy per photon


def test_dose4d_phases_and_accumulation_get_the_one_calibration_factor():
    """absolute_dose4d with [calibration]: every phase result and the accumulated dose are
    multiplied by gy_per_mu · ΣW / D_ref (the same factor as one run), units Gy per fraction."""
    from tetdose.dose.absolute import absolute_dose4d
    from tetdose.dose.accumulate import AccumulatedDose
    from tetdose.dose.dose4d import Dose4D

    rho, lab, _ = reference_phantom(100.0)
    plan = Plan.from_dict({"beam": [_linac(80.0)], "materials": {1: "water"},
                           "calibration": _cal(reference_histories=20_000)})
    r = simulate(rho, plan, TransportSettings(2000, 2, 3, physics="kerma"), labels=lab, progress=False)
    acc = AccumulatedDose(r.dose_gy.copy(), r.dose_std_gy.copy(), r.mass_g, np.ones(1), 0.0)
    d4 = absolute_dose4d(Dose4D(None, [r, r], acc, None), plan)
    s = d4.results[0].record()["calibration_scale"]
    assert s == pytest.approx(calibration_scale(plan, physics=run_physics(r))[0])
    assert d4.results[0].record()["mu_calibration"]["reference_physics"] == "kerma"
    np.testing.assert_allclose(d4.accumulated.dose_gy, r.dose_gy * s)
    for p in d4.results:
        np.testing.assert_allclose(p.dose_gy, r.dose_gy * s)
        assert p.record()["units"]["dose"] == "Gy per fraction"


def test_the_reference_dose_is_computed_with_the_runs_physics():
    """A dose-mode run is calibrated against a reference computed with electrons (absorbed
    dose), a kerma run against kerma: the factor relates like to like, and the record says so.
    Beyond d_max both references agree within their σ (charged-particle equilibrium)."""
    rho, lab, _ = reference_phantom(100.0)
    plan = Plan.from_dict({"beam": [_linac(100.0)], "materials": {1: "water"},
                           "calibration": _cal(reference_histories=40_000)})
    r = simulate(rho, plan, TransportSettings(2000, 2, 3), labels=lab, progress=False)
    dose_rec = absolute_result(r, plan, rho, lab).record()["mu_calibration"]
    assert dose_rec["reference_physics"] == "dose"
    kerma = reference_dose_per_photon("Co60", MUCalibration(**_cal(reference_histories=40_000)),
                                      physics="kerma")
    d, s = dose_rec["reference_gy_per_photon"], dose_rec["reference_gy_per_photon_std"]
    assert abs(d - kerma[0]) < 4 * np.hypot(s, kerma[1])
