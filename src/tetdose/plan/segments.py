"""A linac beam's delivery as sources: one per control-point interval that delivers meterset.

Control points k → k+1 with ΔW_k > 0 deliver ``MU_k = meterset · ΔW_k / (W_last − W_0)``
(:class:`~tetdose.plan.beams.LinacBeam`). An interval in which nothing moves (same jaws, leaves,
isocentre, no turn: a static field or a step-and-shoot segment) is a
:class:`~tetdose.plan.photon_source.PhotonSource` of kind "linac" with its aperture rectangles,
exactly as before control points were interpolated. An interval in which anything moves (an arc,
a sliding-window leaf sweep, jaw tracking) is a :class:`DynamicSegment`: the kernel draws the
meterset fraction t ∈ [0, 1] of each photon continuously, puts the machine at
``state(t) = state_k + t · (state_{k+1} − state_k)`` (angles along their rotation direction,
:func:`~tetdose.plan.beams.rotation_deg`) and aims the photon at a point uniform over the
aperture A(t) of that state.

Weights (equal fluence per MU, :func:`~tetdose.plan.beams.fluence_weight`): a static source has
weight ``MU_k · A / SAD²`` (relative to 100 × 100 mm² at 1000 mm); a dynamic one
``MU_k · Ā_k / SAD²`` with the mean open area ``Ā_k = ∫₀¹ A(t) dt``, and inside it t is drawn
with density ``A(t) / Ā_k`` (rejection against ``A_max``), so every instant of the delivery gets
photons in proportion to its meterset times its solid angle — the same rule as for a sequence
of static fields, which a dynamic segment is the limit of.

Ā and A_max are exact: each jaw and leaf edge is linear in t, so a leaf pair's open width
``max(0, min(x2, p2) − max(x1, p1))`` and its height are piecewise linear, with kinks only where
two of these lines cross; between consecutive crossings the pair's area, and the sum over pairs,
is a quadratic in t. Simpson's rule on every piece integrates it exactly, and each piece's
maximum is at an end or at the vertex of its parabola.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from tetdose._typing import FloatArray
from tetdose.errors import PlanError
from tetdose.plan.beams import (
    MLC,
    ControlPoint,
    LinacBeam,
    aperture_rectangles,
    area_weight,
    beam_axes,
    fluence_weight,
    same_state,
)
from tetdose.plan.photon_source import PhotonSource


@dataclass(frozen=True, eq=False)
class DynamicSegment:
    """The delivery between two control points of a beam while the machine moves (see module
    doc); ``turns_deg``: signed gantry, collimator and couch turns start → end [deg];
    ``meterset``: MU delivered; areas on the isocentre plane [mm²]."""

    kind: ClassVar[str] = "linac_dynamic"
    field_mm: ClassVar[tuple[float, float]] = (0.0, 0.0)
    half_angle_deg: ClassVar[float] = 180.0
    aperture_mm: ClassVar[None] = None

    beam_name: str
    start: ControlPoint
    end: ControlPoint
    turns_deg: tuple[float, float, float]
    isocenter_start_mm: FloatArray
    isocenter_end_mm: FloatArray
    sad_mm: float
    patient_position: str
    energies_mev: FloatArray = field(repr=False)
    line_weights: FloatArray = field(repr=False)
    meterset: float = 0.0
    mean_area_mm2: float = 0.0
    max_area_mm2: float = 0.0

    @property
    def weight(self) -> float:
        """Source weight ``MU · Ā / SAD²`` relative to 100 × 100 mm² at SAD 1000 mm."""
        return area_weight(self.meterset, self.mean_area_mm2, self.sad_mm)

    def angles_at(self, t: float) -> tuple[float, float, float]:
        """Gantry, collimator, couch angles [deg] at meterset fraction ``t`` of the segment."""
        s = self.start
        g, c, u = self.turns_deg
        return ((s.gantry_deg + t * g) % 360.0, (s.collimator_deg + t * c) % 360.0,
                (s.couch_deg + t * u) % 360.0)

    def isocenter_at(self, t: float) -> FloatArray:
        return self.isocenter_start_mm + t * (self.isocenter_end_mm - self.isocenter_start_mm)

    def jaws_at(self, t: float) -> FloatArray:
        return self.start.jaws_mm + t * (self.end.jaws_mm - self.start.jaws_mm)

    def mlc_at(self, t: float) -> MLC | None:
        if self.start.mlc is None or self.end.mlc is None:
            return None
        p0, p1 = self.start.mlc.positions_mm, self.end.mlc.positions_mm
        return self.start.mlc.moved(p0 + t * (p1 - p0))

    def aperture_at(self, t: float) -> FloatArray:
        """Open rectangles [x1, x2, y1, y2] on the isocentre plane [mm] at fraction ``t``."""
        return aperture_rectangles(self.jaws_at(t), self.mlc_at(t))

    def axes_at(self, t: float) -> FloatArray:
        """(3, 3) rows X_b, Y_b, Z_b in the patient frame at fraction ``t``."""
        return beam_axes(*self.angles_at(t), self.patient_position)

    @property
    def position_mm(self) -> FloatArray:
        """Source position at the start [mm] (the kernel moves it with the gantry)."""
        return self.isocenter_start_mm + self.sad_mm * self.axes_at(0.0)[2]

    @property
    def direction(self) -> FloatArray:
        return -self.axes_at(0.0)[2]

    @property
    def e1(self) -> FloatArray:
        return self.axes_at(0.0)[0]

    @property
    def e2(self) -> FloatArray:
        return self.axes_at(0.0)[1]


def beam_sources(beam: LinacBeam) -> list[PhotonSource | DynamicSegment]:
    """The sources of ``beam``: one per control-point interval that delivers meterset and has
    an open aperture (see module doc). A single control point is one static field."""
    cps = beam.control_points
    if len(cps) == 1:
        out = [_static(beam, cps[0], beam.meterset)]
    else:
        total = cps[-1].meterset_weight - cps[0].meterset_weight
        out = []
        for a, b in zip(cps[:-1], cps[1:], strict=True):
            mu = beam.meterset * (b.meterset_weight - a.meterset_weight) / total
            if mu <= 0.0:
                continue
            out.append(_static(beam, a, mu) if same_state(a, b) else _dynamic(beam, a, b, mu))
    out = [s for s in out if s is not None]
    if not out:
        raise PlanError(f"beam {beam.name!r}: every segment is closed (jaws ∩ MLC empty); "
                        "open the leaves (mlc positions_mm, bank 1 then bank 2) inside the jaws")
    return out


def _static(beam: LinacBeam, cp: ControlPoint, mu: float) -> PhotonSource | None:
    rects = aperture_rectangles(cp.jaws_mm, cp.mlc)
    if len(rects) == 0:
        return None
    xb, _yb, zb = beam_axes(cp.gantry_deg, cp.collimator_deg, cp.couch_deg,
                            beam.patient_position)
    return PhotonSource(
        "linac", beam.isocenter_at(cp) + beam.sad_mm * zb, -zb,
        energies_mev=beam.energies_mev, line_weights=beam.line_weights,
        weight=fluence_weight(mu, rects, beam.sad_mm), field_x_direction=xb,
        sad_mm=beam.sad_mm, aperture_mm=rects)


def _dynamic(beam: LinacBeam, a: ControlPoint, b: ControlPoint, mu: float
             ) -> DynamicSegment | None:
    mean, peak = area_mean_and_max(a, b)
    if mean <= 0.0:
        return None
    return DynamicSegment(beam.name, a, b, a.turns_deg(b), beam.isocenter_at(a),
                          beam.isocenter_at(b), beam.sad_mm, beam.patient_position,
                          beam.energies_mev, beam.line_weights, mu, mean, peak)


def open_area_mm2(a: ControlPoint, b: ControlPoint, t: FloatArray) -> FloatArray:
    """Open area A(t) [mm²] of the aperture interpolated between ``a`` (t = 0) and ``b``."""
    t = np.asarray(t, dtype=np.float64).reshape(-1, 1)
    j = a.jaws_mm + t * (b.jaws_mm - a.jaws_mm)  # (T, 4)
    if a.mlc is None or b.mlc is None:
        return np.clip(j[:, 1] - j[:, 0], 0, None) * np.clip(j[:, 3] - j[:, 2], 0, None)
    n = len(a.mlc.boundaries_mm) - 1
    p = a.mlc.positions_mm + t * (b.mlc.positions_mm - a.mlc.positions_mm)  # (T, 2N)
    bnd = a.mlc.boundaries_mm
    move, fixed = (j[:, 0:2], j[:, 2:4]) if a.mlc.axis == "X" else (j[:, 2:4], j[:, 0:2])
    along = np.clip(np.minimum(move[:, 1:2], p[:, n:]) - np.maximum(move[:, 0:1], p[:, :n]),
                    0, None)
    across = np.clip(np.minimum(fixed[:, 1:2], bnd[1:]) - np.maximum(fixed[:, 0:1], bnd[:-1]),
                     0, None)
    return np.sum(along * across, axis=1)


def _crossings(f0: FloatArray, f1: FloatArray, g0: FloatArray, g1: FloatArray) -> FloatArray:
    """t ∈ (0, 1) where the lines f(t) = f0 + t(f1 − f0) and g(t) cross."""
    d0, d1 = np.broadcast_arrays(np.asarray(f0) - g0, np.asarray(f1) - g1)
    cross = d0 * d1 < 0.0
    return d0[cross] / (d0[cross] - d1[cross])


def _kinks(a: ControlPoint, b: ControlPoint) -> FloatArray:
    """Every t ∈ (0, 1) where a leaf pair's open width or height may change slope."""
    ja, jb = a.jaws_mm, b.jaws_mm
    out = [_crossings(ja[0], jb[0], ja[1], jb[1]), _crossings(ja[2], jb[2], ja[3], jb[3])]
    if a.mlc is not None and b.mlc is not None:
        n = len(a.mlc.boundaries_mm) - 1
        pa, pb, bnd = a.mlc.positions_mm, b.mlc.positions_mm, a.mlc.boundaries_mm
        m, f = ((0, 1), (2, 3)) if a.mlc.axis == "X" else ((2, 3), (0, 1))
        lines = [(ja[m[0]], jb[m[0]]), (ja[m[1]], jb[m[1]]), (pa[:n], pb[:n]), (pa[n:], pb[n:])]
        for i, (f0, f1) in enumerate(lines):
            for g0, g1 in lines[i + 1:]:
                out.append(_crossings(f0, f1, g0, g1))
        for k in f:
            for edge in (bnd[:-1], bnd[1:]):
                out.append(_crossings(ja[k], jb[k], edge, edge))
    return np.concatenate(out)


def area_mean_and_max(a: ControlPoint, b: ControlPoint) -> tuple[float, float]:
    """(Ā = ∫₀¹ A(t) dt, max A) [mm²] of the aperture interpolated from ``a`` to ``b``, exact
    (piecewise quadratic between the kinks, see module doc)."""
    knots = np.unique(np.concatenate([[0.0, 1.0], np.clip(_kinks(a, b), 0.0, 1.0)]))
    lo, hi = knots[:-1], knots[1:]
    f = open_area_mm2(a, b, np.concatenate([lo, 0.5 * (lo + hi), hi])).reshape(3, -1)
    fa, fm, fb = f
    mean = float(np.sum((hi - lo) / 6.0 * (fa + 4.0 * fm + fb)))
    lin, quad = -3.0 * fa + 4.0 * fm - fb, 2.0 * fa - 4.0 * fm + 2.0 * fb  # q(s) = fa + lin s + quad s²
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(quad < 0.0, -lin / (2.0 * quad), -1.0)
    inside = (s > 0.0) & (s < 1.0)
    vertex = np.where(inside, fa + lin * s + quad * s * s, 0.0)
    return mean, float(max(f.max(), vertex.max()))
