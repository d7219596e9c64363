"""Interplay of a delivery with breathing: one fraction's dose, each phase getting only the part
of the plan delivered while the patient is in it.

:func:`tetdose.dose.dose4d.run_dose4d` gives every phase the whole plan, weighted by its time
share: the dose of a delivery infinitely slow against breathing. Here the plan's
:class:`~tetdose.plan.delivery.Timeline` is cut by the patient's phase in time
(:mod:`tetdose.motion.trace`, :mod:`tetdose.plan.phase_split`): phase p transports only the
control-point pieces delivered in it, with source weight W_p (MU × aperture solid angle, so
photons ∝ W_p) and n_p = n · K · W_p / W histories (K phases, W = Σ_p W_p, the plan's). Its
dose per source photon D_p is accumulated with the weights W_p / W,

    D = Σ_p (W_p / W) E_p / m   (mass kept per tet, :mod:`tetdose.dose.accumulate`),

i.e. dose per source photon of the whole plan: the unit of ``run_dose4d`` without a trace, and
the same absolute scale with ``[calibration]`` (from the plan's MU). When every phase gets the
time share τ_p of every control point, W_p / W = τ_p and D_p is the phase's dose of the whole
plan, so D is the time-weighted 4D dose (Bortfeld et al., Phys. Med. Biol. 47:2203, 2002: the
interplay averages out over many fractions). A ``[prescription]`` would rescale each fraction
to its prescribed dose and hide the interplay; it is refused.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from tetdose._typing import FloatArray
from tetdose.dose.dose4d import Dose4D, run_dose4d
from tetdose.errors import OptionError
from tetdose.motion.phases import PhaseSeries
from tetdose.plan.delivery import Timeline
from tetdose.plan.phase_split import PhaseDelivery, split_by_phase
from tetdose.transport import Plan, TransportSettings


def check_interplay_plan(plan: Plan) -> None:
    """Refuse what has no delivery in time or would hide the interplay (module doc)."""
    if plan.beams or plan.volume_sources or not plan.treatment_beams:
        raise OptionError("the delivery in time needs linac beams only (type = \"linac\" or an "
                          "RT Plan); pencil, parallel, point and volume sources have no MU")
    if plan.prescription is not None:
        raise OptionError("[prescription] rescales each fraction to its prescribed dose and "
                          "hides the interplay; drop it (dose per source photon) or give "
                          "[calibration] gy_per_mu (Gy from the MU)")


def phase_histories(weights: FloatArray, n_histories: int, n_batches: int) -> FloatArray:
    """n_p = round(n · K · W_p / W), at least ``n_batches`` where W_p > 0 (0 elsewhere)."""
    w = np.asarray(weights, dtype=np.float64)
    n = np.rint(n_histories * len(w) * w / w.sum()).astype(np.int64)
    return np.where(w > 0.0, np.maximum(n, n_batches), 0)


def run_interplay(series: PhaseSeries, plan: Plan, settings: TransportSettings,
                  timeline: Timeline, starts_s: FloatArray, phase_index: FloatArray, *,
                  t0_s: float = 0.0, fraction: int = 1, trace: dict[str, Any] | None = None,
                  phase_ct: list[Any] | None = None, dvfs: list[Any] | None = None,
                  phase_density: list[Any] | None = None, **kwargs: Any) -> Dose4D:  # noqa: ANN401
    """One fraction: ``timeline`` started at ``t0_s`` on the clock of the phase intervals
    (``starts_s``, ``phase_index``), each phase transporting its share (module doc) with random
    stream ``fraction · K + p`` (fraction ≥ 1: independent of run_dose4d's streams 0..K−1).
    Phases that get no MU are not transported. ``kwargs``: as
    :func:`~tetdose.dose.dose4d.run_dose4d` (``ct_hu``, ``voxel_engine``, ...); ``phase_ct``,
    ``dvfs`` and ``phase_density`` are given for every phase of ``series``."""
    check_interplay_plan(plan)
    plan = plan.resolved(series.reference)  # isocenter = "structure" → its planning centroid
    timeline = timeline.with_beams(plan.treatment_beams)
    k = series.n_phases
    delivery = split_by_phase(timeline, starts_s, phase_index, k, t0_s)
    weights = delivery.source_weights(plan)
    keep = np.flatnonzero(weights > 0.0)
    hist = phase_histories(weights, settings.n_histories, settings.n_batches)
    sub = PhaseSeries(series.reference, series.points_mm[keep], series.phase_percent[keep],
                      weights[keep] / weights.sum(),
                      None if series.density_g_cm3 is None else series.density_g_cm3[keep])
    plans = [delivery.plan(int(p), plan) for p in keep]
    sets = [replace(settings, n_histories=int(hist[p]), stream=fraction * k + int(p))
            for p in keep]
    pick = {name: None if v is None else [v[p] for p in keep]
            for name, v in (("phase_ct", phase_ct), ("dvfs", dvfs),
                            ("phase_density", phase_density))}
    d4 = run_dose4d(sub, plan, settings, phase_plans=plans, phase_settings=sets, **pick,
                    **kwargs)
    return replace(d4, delivery=delivery_record(series, delivery, weights, timeline, t0_s,
                                                trace))


def delivery_record(series: PhaseSeries, delivery: PhaseDelivery, weights: FloatArray,
                    timeline: Timeline, t0_s: float, trace: dict[str, Any] | None
                    ) -> dict[str, object]:
    """``summary.json``'s ``delivery``: MU and photon share per phase (phase order), the
    timeline and the trace."""
    return {**timeline.record(), "start_s": float(t0_s), "trace": trace or {},
            "phase_percent": [float(p) for p in series.phase_percent],
            "mu_per_phase": [float(m) for m in delivery.mu],
            "photon_share_per_phase": [float(w) for w in weights / weights.sum()]}
