"""Doses in Gy per fraction: a run's dose per source photon times one factor s (source photons
per fraction), from the plan's ``[prescription]`` (s = D_Rx / M(D) on the structure,
:mod:`tetdose.plan.prescription`) or its ``[calibration]`` (s = gy_per_mu · ΣW / D_ref,
:mod:`tetdose.plan.mu_calibration`). The same s multiplies every output of a run — per phase and
accumulated, mesh and voxel — and is written into the run records; without either, doses stay in
"Gy per source photon".
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace
from functools import lru_cache
from typing import TYPE_CHECKING, Any

from tetdose.errors import PlanError
from tetdose.plan.mu_calibration import (
    MU_UNIT,
    REFERENCE_JAWS_MM,
    REFERENCE_SAD_MM,
    MUCalibration,
    reference_phantom,
)
from tetdose.plan.prescription import (
    PER_PHOTON_UNIT,
    record,
    region_cells,
    region_label,
    scale_for,
)
from tetdose.plan.spectra import build_up_depth_mm, is_named
from tetdose.transport import Plan, TransportSettings, simulate
from tetdose.transport.run.settings import ELECTRON_CUTOFF_MEV

if TYPE_CHECKING:
    from tetdose.dose.dose4d import Dose4D
    from tetdose.transport.history.result import DoseResult


def plan_weight_and_quality(plan: Any) -> tuple[float, str]:  # noqa: ANN401
    """(ΣW of the plan's linac sources, their one beam quality); refuses other plans."""
    plan.require_resolved()  # an unresolved isocentre has no sources yet: ΣW would miss it
    if plan.beams:
        raise PlanError("[calibration] gy_per_mu needs linac beams only (MU have no meaning for "
                        "pencil/parallel/point sources); use [prescription] instead")
    qualities = {b.spectrum for b in plan.treatment_beams}
    if len(qualities) != 1:
        raise PlanError(f"[calibration] holds for one beam quality, the plan has "
                        f"{sorted(qualities)}; split the plan by beam quality")
    return float(sum(s.weight for s in plan.sources)), qualities.pop()


def reference_dose_per_photon(spectrum: str, cal: MUCalibration, seed: int = 1,
                              physics: str = "dose", electron_cutoff_mev: float | None = None
                              ) -> tuple[float, float]:
    """(D_ref, σ) [Gy per source photon] in the reference conditions of ``cal`` (module doc),
    computed with the run's ``physics``: absorbed dose (electrons transported, cut-off
    ``electron_cutoff_mev``, default the settings' default) or, for a kerma run, kerma — so
    the calibration factor relates like to like. Kerma is refused in the build-up region."""
    if physics == "kerma" and is_named(spectrum) and cal.depth_mm < build_up_depth_mm(spectrum):
        raise PlanError(f"[calibration] depth_mm = {cal.depth_mm:g} lies in the build-up region "
                        f"of {spectrum} (d_max {build_up_depth_mm(spectrum):g} mm), where a "
                        "kerma run reports kerma, not dose; state gy_per_mu at 100 mm depth, or "
                        "run with --physics dose")
    cutoff = ELECTRON_CUTOFF_MEV if electron_cutoff_mev is None else float(electron_cutoff_mev)
    return _reference(spectrum, cal.depth_mm, cal.ssd_mm, int(cal.reference_histories), seed,
                      physics, cutoff)


@lru_cache(maxsize=8)
def _reference(spectrum: str, depth_mm: float, ssd_mm: float, n: int, seed: int,
               physics: str, electron_cutoff_mev: float) -> tuple[float, float]:
    rho, lab, index = reference_phantom(depth_mm)
    iso_y = REFERENCE_SAD_MM - ssd_mm  # surface at y = 0, beam along +y (HFS, gantry 0)
    plan = Plan.from_dict({"beam": [{"type": "linac", "spectrum": spectrum,
                                     "isocenter_mm": [0.0, iso_y, 0.0],
                                     "jaws_mm": list(REFERENCE_JAWS_MM)}],
                           "materials": {1: "water"}})
    r = simulate(rho, plan, TransportSettings(n, 10, seed, physics=physics,
                                              electron_cutoff_mev=electron_cutoff_mev),
                 labels=lab, progress=False)
    return float(r.dose_gy[index]), float(r.dose_std_gy[index])


def run_physics(result: DoseResult | None) -> dict[str, Any]:
    """The physics and electron cut-off a result was computed with (its record), as keyword
    arguments of :func:`reference_dose_per_photon`; dose with the default cut-off if unknown."""
    extra = {} if result is None else result.extra
    return {"physics": extra.get("physics", "dose"),
            "electron_cutoff_mev": extra.get("electron_cutoff_mev")}


def calibration_scale(plan: Any, seed: int = 1,  # noqa: ANN401
                      physics: Mapping[str, Any] | None = None) -> tuple[float, dict[str, Any]]:
    """(source photons per fraction, run-record entries) of ``plan.calibration``; the reference
    dose is computed with ``physics`` (:func:`run_physics` of the run being calibrated)."""
    cal = plan.calibration
    w, quality = plan_weight_and_quality(plan)
    phys = dict(physics or run_physics(None))
    d_ref, s_ref = reference_dose_per_photon(quality, cal, seed, **phys)
    if d_ref <= 0.0:
        raise PlanError("the reference computation scored no dose; raise "
                        "[calibration] reference_histories")
    scale = cal.gy_per_mu * w / d_ref
    rec = {"mu_calibration": {
        "gy_per_mu": cal.gy_per_mu, "beam_quality": quality,
        "reference": f"water, SSD {cal.ssd_mm:g} mm, 100 x 100 mm2 at SAD 1000 mm, "
                     f"depth {cal.depth_mm:g} mm on the axis",
        "reference_gy_per_photon": d_ref, "reference_gy_per_photon_std": s_ref,
        "reference_histories": int(cal.reference_histories),
        "reference_physics": phys["physics"],
        "mu_field_weight": w, "mu": float(sum(b.meterset for b in plan.treatment_beams))},
        "calibration_scale": scale, "units": {"dose": MU_UNIT}}
    return scale, rec


def absolute_result(result: DoseResult, plan: Any, geometry: Any,  # noqa: ANN401
                     labels: Any = None) -> DoseResult:
    """One run prescribed by ``plan.prescription`` or calibrated by ``plan.calibration``
    (gy_per_mu, :mod:`tetdose.plan.mu_calibration`); unchanged without either."""
    if getattr(plan, "calibration", None) is not None:
        scale, rec = calibration_scale(plan, physics=run_physics(result))
        return _scaled(result, scale, rec)
    rx = plan.prescription
    if rx is None:
        return result.with_extra(units={"dose": PER_PHOTON_UNIT})
    mask = region_cells(geometry, labels, region_label(rx.structure, plan.regions))
    scale = scale_for(rx, result.dose_gy, result.mass_g, mask)
    return _scaled(result, scale, record(rx, scale))


def absolute_dose4d(d4: Dose4D, plan: Any) -> Dose4D:  # noqa: ANN401
    """Every phase and accumulation of ``d4`` scaled by one factor, fixed on the accumulated
    mesh dose of the prescription structure (unchanged without a prescription). With
    ``plan.calibration`` (gy_per_mu) the factor comes from the meterset instead."""
    rx = plan.prescription
    acc = d4.accumulated
    if getattr(plan, "calibration", None) is not None:
        s, rec = calibration_scale(plan, physics=run_physics(d4.results[0] if d4.results else None))
    elif rx is None:
        return d4
    else:
        ref = d4.series.reference
        mask = region_cells(ref, None, region_label(rx.structure, plan.regions))
        s = scale_for(rx, acc.dose_gy, acc.mass_g, mask)
        rec = record(rx, s)
    acc = replace(acc, dose_gy=acc.dose_gy * s,
                  dose_std_gy=None if acc.dose_std_gy is None else acc.dose_std_gy * s)
    voxel = d4.voxel
    if voxel is not None:
        voxel = replace(_scaled_images(voxel, s),
                        results=[_scaled(r, s, rec) for r in voxel.results])
    parts = {"body": _scaled_images(d4.body, s)} if getattr(d4, "body", None) else {}
    return replace(d4, results=[_scaled(r, s, rec) for r in d4.results], accumulated=acc,
                   voxel=voxel, **parts)


def _scaled(result: DoseResult, scale: float, rec: dict[str, Any]) -> DoseResult:
    """``result`` times ``scale`` (normalization particles × scale), ``rec`` in its record."""
    return replace(result.with_extra(**rec), particles=result.particles * scale)


#: Dose images of the 4D results (voxel way, hybrid body part) that a prescription scales.
_DOSE_IMAGES = ("direct_mapping", "energy_mass_transfer", "direct_mapping_std",
                "energy_mass_transfer_std", "accumulated", "accumulated_std", "combined")


def _scaled_images(obj: Any, s: float) -> Any:  # noqa: ANN401
    """``obj`` (a dataclass) with each dose image of :data:`_DOSE_IMAGES` it has times ``s``."""
    changes = {k: getattr(obj, k).with_array(getattr(obj, k).array * s) for k in _DOSE_IMAGES
               if getattr(obj, k, None) is not None}
    return replace(obj, **changes)
