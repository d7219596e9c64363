"""A delivery cut by the breathing phases: the control-point intervals delivered in each phase.

The patient's phase is piecewise constant in time: phase ``phase_index[i]`` from
``starts_s[i]`` to ``starts_s[i + 1]`` (a breathing trace or a regular cycle,
:mod:`tetdose.motion.trace`). A control-point interval of the :class:`~tetdose.plan.delivery.
Timeline` delivered over [t_a, t_b] moves the machine at constant speed (its meterset grows
linearly in time), so the part of it delivered over [t_1, t_2] ⊂ [t_a, t_b] is the interval
between the machine states at u_1 = (t_1 − t_a)/(t_b − t_a) and u_2, carrying MU_k (u_2 − u_1):
every angle, jaw, leaf and the isocentre interpolated as in :mod:`tetdose.plan.segments`. Each
phase gets, per beam, a :class:`~tetdose.plan.beams.LinacBeam` made of its pieces in time order,
joined by intervals of zero meterset (which deliver nothing), so the pieces of all phases add up
to the plan exactly — the same sources, cut where the patient changes phase. The MU of a
control point spanning phases is thereby split in proportion to the time spent in each.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from tetdose._typing import FloatArray
from tetdose.errors import PlanError
from tetdose.plan.beams import CW_SENSE, ControlPoint, LinacBeam
from tetdose.plan.delivery import BeamTimeline, Timeline
from tetdose.plan.model import Plan
from tetdose.plan.segments import area_mean_and_max

#: Turns below this [deg] within one piece are treated as no turn.
MIN_TURN_DEG = 1e-6


@dataclass(frozen=True, eq=False)
class PhaseDelivery:
    """Per phase: the linac beams delivered in it (possibly none) and its MU."""

    beams: tuple[tuple[LinacBeam, ...], ...]
    mu: FloatArray

    def plan(self, phase: int, base: Plan) -> Plan | None:
        """``base``'s materials, regions and normalization with phase ``phase``'s beams (None
        if it gets no MU); no prescription or calibration: one scale is fixed on the whole plan."""
        if not self.beams[phase]:
            return None
        return Plan(materials=base.materials, particles=base.particles,
                    treatment_beams=self.beams[phase], regions=base.regions)

    def source_weights(self, base: Plan) -> FloatArray:
        """Σ source weight (MU × aperture solid angle, :func:`~tetdose.plan.beams.fluence_weight`)
        of each phase's plan: the share of the plan's photons delivered in it."""
        return np.array([0.0 if (p := self.plan(k, base)) is None
                         else sum(s.weight for s in p.sources) for k in range(len(self.beams))])


def split_by_phase(timeline: Timeline, starts_s: FloatArray, phase_index: FloatArray,
                   n_phases: int, t0_s: float = 0.0) -> PhaseDelivery:
    """Cut ``timeline`` (started at ``t0_s`` on the phase clock) by the phase intervals
    (module doc) into one set of beams per phase."""
    starts = np.asarray(starts_s, dtype=np.float64).reshape(-1)
    idx = np.asarray(phase_index).astype(np.int64).reshape(-1)
    if len(starts) != len(idx) or len(starts) == 0 or np.any(np.diff(starts) <= 0.0):
        raise PlanError("phase intervals need increasing start times, one phase each")
    if np.any((idx < 0) | (idx >= n_phases)):
        raise PlanError(f"phase indices must lie in 0..{n_phases - 1}")
    if t0_s < starts[0]:
        raise PlanError(f"the delivery starts at {t0_s:g} s, before the breathing trace "
                        f"({starts[0]:g} s)")
    per_phase: list[list[LinacBeam]] = [[] for _ in range(n_phases)]
    mu = np.zeros(n_phases)
    for bt in timeline.beams:
        pieces = _pieces(bt, starts, idx, t0_s)
        for p in range(n_phases):
            mine = [x for x in pieces if x[0] == p]
            if mine:
                per_phase[p].append(_phase_beam(bt.beam, mine))
                mu[p] += sum(x[4] for x in mine)
    return PhaseDelivery(tuple(tuple(b) for b in per_phase), mu)


def _pieces(bt: BeamTimeline, starts: FloatArray, idx: FloatArray, t0_s: float
            ) -> list[tuple[int, ControlPoint, ControlPoint, tuple[float, ...], float, float,
                            float]]:
    """(phase, a, b, turns, MU, u1, u2) of every open piece of the beam's intervals."""
    out = []
    times = bt.times_s + t0_s
    for k, (a, b) in enumerate(bt.intervals()):
        if bt.mu[k] <= 0.0 or area_mean_and_max(a, b)[0] <= 0.0:
            continue
        ta, tb = times[k], times[k + 1]
        cuts = starts[(starts > ta) & (starts < tb)]
        edges = np.concatenate([[ta], cuts, [tb]])
        turns = a.turns_deg(b) if a is not b else (0.0, 0.0, 0.0)
        for t1, t2 in zip(edges[:-1], edges[1:], strict=True):
            u1, u2 = (t1 - ta) / (tb - ta), (t2 - ta) / (tb - ta)
            phase = int(idx[np.searchsorted(starts, t1, side="right") - 1])
            out.append((phase, a, b, turns, float(bt.mu[k] * (u2 - u1)), float(u1), float(u2)))
    return out


def _phase_beam(beam: LinacBeam, pieces: list) -> LinacBeam:
    """``beam``'s pieces delivered in one phase as one beam (module doc)."""
    cps, w = [], 0.0
    for _phase, a, b, turns, mu, u1, u2 in pieces:
        cps.extend(_piece(beam, a, b, turns, u1, u2, w, w + mu))
        w += mu
    for k in range(1, len(cps) - 1, 2):  # a piece's end → the next piece's start: no MU
        cps[k] = _standing(cps[k], cps[k + 1])
    return replace(beam, control_points=tuple(cps), meterset=w, isocenter_region=None)


def _standing(end: ControlPoint, nxt: ControlPoint) -> ControlPoint:
    """``end`` with direction NONE on every axis whose angle the next piece starts at: two
    pieces that meet (one interval cut only by other phases' time, or adjacent intervals) do not
    turn between them — CW/CC there would read as a full turn (DICOM C.8.8.14.8)."""
    still = {f"{name}_rotation": "NONE" for name in ("gantry", "collimator", "couch")
             if abs((getattr(nxt, f"{name}_deg") - getattr(end, f"{name}_deg") + 180.0) % 360.0
                    - 180.0) < 1e-9}
    return replace(end, **still) if still else end


def _piece(beam: LinacBeam, a: ControlPoint, b: ControlPoint, turns: tuple[float, ...],
           u1: float, u2: float, w1: float, w2: float) -> tuple[ControlPoint, ControlPoint]:
    """The machine states at u1 and u2 of interval a → b, with the rotation directions of the
    turns between them and the cumulative meterset weights w1, w2."""
    names = ("gantry", "collimator", "couch")
    start: dict = {"meterset_weight": w1}
    end: dict = {"meterset_weight": w2}
    for name, turn in zip(names, turns, strict=True):
        a0 = getattr(a, f"{name}_deg")
        piece = (u2 - u1) * turn
        if abs(piece) < MIN_TURN_DEG:
            direction, piece = "NONE", 0.0
        else:
            direction = "CW" if (piece > 0.0) == (CW_SENSE[name] > 0.0) else "CC"
        first = (a0 + u1 * turn) % 360.0
        start[f"{name}_deg"], end[f"{name}_deg"] = first, (first + piece) % 360.0
        start[f"{name}_rotation"] = end[f"{name}_rotation"] = direction
    iso_a, iso_b = beam.isocenter_at(a), beam.isocenter_at(b)
    for state, u in ((start, u1), (end, u2)):
        state["jaws_mm"] = a.jaws_mm + u * (b.jaws_mm - a.jaws_mm)
        state["isocenter_mm"] = iso_a + u * (iso_b - iso_a)
        state["mlc"] = None if a.mlc is None else a.mlc.moved(
            a.mlc.positions_mm + u * (b.mlc.positions_mm - a.mlc.positions_mm))
    return ControlPoint(**start), ControlPoint(**end)
