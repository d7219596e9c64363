"""The delivery in time: when each control point of a plan's linac beams is reached.

Between control points k and k+1 a beam delivers ``MU_k = meterset · ΔW_k / (W_last − W_0)``
while the gantry turns by Δg_k [deg] and each leaf travels |Δx| [mm]. The machine runs as fast
as its slowest limit allows, at a constant speed within the interval:

    T_k = max(MU_k / Ṙ_k, |Δg_k| / ġ_max, max_leaf |Δx| / ẋ_max)       [s]

with the dose rate Ṙ_k [MU/s] (the RT Plan's DoseRateSet of control point k where present,
else the beam's ``dose_rate_mu_per_min``, default 600 MU/min), the largest gantry speed
ġ_max (``max_gantry_deg_per_s``, default 6 °/s) and the largest leaf speed ẋ_max
(``max_leaf_mm_per_s``; no limit unless given). This is the usual model of a VMAT delivery
(e.g. Otto, Med. Phys. 35:310, 2008: the dose rate and gantry speed vary so that one of them is
at its limit). An interval with ΔW = 0 (leaves moving between step-and-shoot segments) takes the
time of its motion and delivers nothing. Beams follow one another in plan order, each starting
``beam_gap_s`` (default 0) after the previous one ends. Within an interval the meterset, and so
every machine parameter, grows linearly in time (the constant speed above), which is what
:mod:`tetdose.plan.phase_split` uses to cut an interval at a given instant.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from tetdose._typing import FloatArray
from tetdose.errors import PlanError
from tetdose.plan.beams import ControlPoint, LinacBeam

#: Defaults of the machine's limits (plan.toml ``[[beam]]`` keys of the same names).
DOSE_RATE_MU_PER_MIN = 600.0
MAX_GANTRY_DEG_PER_S = 6.0
BEAM_GAP_S = 0.0


@dataclass(frozen=True, eq=False)
class BeamTimeline:
    """One beam's delivery: the time [s, from the start of the first beam] of each control
    point and the MU of each interval. A single control point (a static field) is the interval
    from that control point to itself."""

    beam: LinacBeam
    times_s: FloatArray  # (n_intervals + 1,)
    mu: FloatArray  # (n_intervals,)

    def intervals(self) -> list[tuple[ControlPoint, ControlPoint]]:
        """The control-point pairs (start, end) of the intervals, in time order."""
        cps = self.beam.control_points
        return [(cps[0], cps[0])] if len(cps) == 1 else list(zip(cps[:-1], cps[1:], strict=True))

    @property
    def beam_on_s(self) -> float:
        """Time spent in intervals that deliver MU [s]."""
        return float(np.sum(np.diff(self.times_s)[self.mu > 0.0]))


@dataclass(frozen=True, eq=False)
class Timeline:
    """Every linac beam of a plan in delivery order (module doc)."""

    beams: tuple[BeamTimeline, ...]

    @property
    def end_s(self) -> float:
        """The end of the last beam [s]."""
        return float(self.beams[-1].times_s[-1])

    @property
    def beam_on_s(self) -> float:
        return float(sum(b.beam_on_s for b in self.beams))

    @property
    def total_mu(self) -> float:
        return float(sum(b.mu.sum() for b in self.beams))

    def with_beams(self, beams: Sequence[LinacBeam]) -> Timeline:
        """The same times with ``beams`` (e.g. the plan's, their isocentres resolved)."""
        if len(beams) != len(self.beams):
            raise PlanError(f"{len(beams)} beams for a timeline of {len(self.beams)}")
        return Timeline(tuple(BeamTimeline(b, t.times_s, t.mu)
                              for b, t in zip(beams, self.beams, strict=True)))

    def record(self) -> dict[str, object]:
        """JSON-ready summary: beam-on and total time [s], MU and each beam's span."""
        return {"beam_on_s": self.beam_on_s, "delivery_s": self.end_s, "mu": self.total_mu,
                "beams": [{"name": b.beam.name, "start_s": float(b.times_s[0]),
                           "end_s": float(b.times_s[-1]), "mu": float(b.mu.sum()),
                           "control_points": len(b.beam.control_points)} for b in self.beams]}


def interval_mu(beam: LinacBeam) -> FloatArray:
    """MU of each control-point interval of ``beam`` (one value for a static field)."""
    cps = beam.control_points
    if len(cps) == 1:
        return np.array([beam.meterset])
    w = np.array([c.meterset_weight for c in cps])
    return beam.meterset * np.diff(w) / (w[-1] - w[0])


def interval_durations_s(beam: LinacBeam, dose_rates_mu_per_min: Sequence[float | None] | None
                         = None) -> FloatArray:
    """T_k [s] of every interval of ``beam`` (module doc); ``dose_rates_mu_per_min``: one per
    control point (None where not set: the beam's rate)."""
    m = beam.machine
    default_rate = m.get("dose_rate_mu_per_min", DOSE_RATE_MU_PER_MIN)
    gantry = m.get("max_gantry_deg_per_s", MAX_GANTRY_DEG_PER_S)
    leaf = m.get("max_leaf_mm_per_s")
    mu = interval_mu(beam)
    rates = np.full(len(mu), default_rate)
    if dose_rates_mu_per_min is not None:
        given = list(dose_rates_mu_per_min)
        if len(given) != len(beam.control_points):
            raise PlanError(f"beam {beam.name!r}: {len(given)} dose rates for "
                            f"{len(beam.control_points)} control points")
        rates = np.array([default_rate if r is None else float(r) for r in given[:len(mu)]])
    if np.any(rates <= 0.0):
        raise PlanError(f"beam {beam.name!r}: dose rates must be positive (MU/min)")
    out = mu / (rates / 60.0)
    for k, (a, b) in enumerate(BeamTimeline(beam, np.zeros(1), mu).intervals()):
        out[k] = max(out[k], abs(a.turns_deg(b)[0]) / gantry if a is not b else 0.0)
        if leaf is not None and a.mlc is not None and b.mlc is not None:
            out[k] = max(out[k], float(np.max(np.abs(b.mlc.positions_mm - a.mlc.positions_mm)))
                         / leaf)
    return out


def delivery_timeline(beams: Sequence[LinacBeam],
                      dose_rates: Mapping[str, Sequence[float | None]] | None = None
                      ) -> Timeline:
    """The :class:`Timeline` of ``beams`` delivered in order (module doc); ``dose_rates``:
    beam name → dose rate [MU/min] per control point (:func:`rt_plan_dose_rates`)."""
    if not beams:
        raise PlanError("a delivery timeline needs linac beams (type = \"linac\" or an RT Plan)")
    out, t = [], 0.0
    for i, beam in enumerate(beams):
        if i > 0:
            t += beam.machine.get("beam_gap_s", BEAM_GAP_S)
        rates = None if dose_rates is None else dose_rates.get(beam.name)
        times = t + np.concatenate([[0.0], np.cumsum(interval_durations_s(beam, rates))])
        out.append(BeamTimeline(beam, times, interval_mu(beam)))
        t = float(times[-1])
    return Timeline(tuple(out))


def rt_plan_dose_rates(path: str | os.PathLike[str]) -> dict[str, list[float | None]]:
    """Beam name → DoseRateSet [MU/min] of each control point of a DICOM RT Plan (an absent
    value carries the previous one forward, DICOM PS3.3 C.8.8.14; None before the first)."""
    from tetdose._optional import import_optional

    pydicom = import_optional("pydicom", "dicom", "reading an RT Plan's dose rates")
    ds = pydicom.dcmread(str(path), stop_before_pixels=True)
    out: dict[str, list[float | None]] = {}
    for beam in getattr(ds, "BeamSequence", []):
        rate: float | None = None
        rates = []
        for cp in getattr(beam, "ControlPointSequence", []):
            if "DoseRateSet" in cp:
                rate = float(cp.DoseRateSet)
            rates.append(rate)
        out[str(beam.get("BeamName", "") or beam.BeamNumber)] = rates
    return out
