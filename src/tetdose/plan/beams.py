"""Linac treatment beams: IEC 61217 gantry/collimator/couch angles → DICOM patient frame, and the
control points that describe a delivery (static fields, step-and-shoot, sliding window, arcs).

Coordinate systems (IEC 61217, all rotations right-handed about their axis, i.e. clockwise seen
from the origin looking along the positive axis):

- Fixed system f: X_f to the right of an observer at the couch foot facing the gantry, Y_f from
  the isocentre towards the gantry, Z_f up. Gantry system g = R_y(gantry)·f: the source sits at
  +SAD·Z_g, so at gantry 0 it is above the isocentre and at gantry 90 on the +X_f side.
- Beam limiting device system b = R_z(collimator)·g: the X jaws (X1 negative, X2 positive) and
  MLCX leaves move along X_b, the Y jaws and MLCY leaves along Y_b. Aperture coordinates are in
  mm projected to the isocentre plane, as in DICOM RT Plan.
- Patient support system s = R_z(couch)·f (couch rotation about the vertical through the
  isocentre). The patient lies on the couch in the table-top frame (no pitch/roll here).
- DICOM patient frame (LPS: +x patient left, +y posterior, +z head) from s by the patient
  position (DICOM PS3.3 C.8.8.25.6.2): HFS x_s = x, y_s = z, z_s = −y; HFP x_s = −x, y_s = z,
  z_s = y; FFS x_s = −x, y_s = −z, z_s = −y; FFP x_s = x, y_s = −z, z_s = y.

So for HFS at gantry 0 the beam travels anterior → posterior (+y), at gantry 90 it comes from
the patient's left and travels −x. The photon source model: a point source at SAD on the
central axis; each photon aims at a point drawn uniformly over the open aperture on the
isocentre plane (jaws ∩ MLC, a union of rectangles), so the fluence is uniform on that plane
(a flattened beam), falls off as (SAD/d)² along rays and is sharp at the geometric field edge
(no source size, no head scatter, no leaf transmission). Segments and beams are drawn in
proportion to meterset × aperture solid angle (:func:`fluence_weight`): equal fluence per MU.

Control points (DICOM PS3.3 C.8.8.14.5): a beam is a sequence of machine states with a
cumulative meterset weight W_k. Between control points k and k+1 the meterset ΔW_k is delivered
while every parameter moves linearly in meterset: jaws, leaves and isocentre, and the gantry,
collimator and couch angles along their rotation direction (C.8.8.14.8: a rotation from a to b
CW/CC is the turn of at most 360° in that sense, a → a CW is a full turn; "NONE" with a ≠ b is
read as the shorter turn; an angle that a later control point omits does not turn towards it).
A beam whose gantry, collimator or couch sweeps more than :data:`MAX_SWEEP_DEG` is refused.
Step-and-shoot is the special case of equal apertures at k and k+1 (and ΔW = 0 between
segments); a single control point is a static field. The sampling of that
continuous delivery is in :mod:`tetdose.plan.segments`.

Rotation senses (IEC 61217 angles increase clockwise seen from the origin along the positive
axis): gantry (seen from the isocentre, looking at the gantry) and collimator (seen from the
isocentre, looking at the source) turn CW with increasing angle; the couch is seen from above,
against its +Z axis, so its angle increases CC (DICOM C.8.8.14.8, example 3: table 170° → 160°
CC is a turn of 350°).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from tetdose._typing import FloatArray
from tetdose.errors import PlanError

PATIENT_POSITIONS = ("HFS", "HFP", "FFS", "FFP")
#: Rows: DICOM patient axes (x, y, z) expressed in the patient support system s.
_PATIENT_TO_S = {
    "HFS": np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]]),
    "HFP": np.array([[-1.0, 0, 0], [0, 0, 1.0], [0, 1.0, 0]]),
    "FFS": np.array([[-1.0, 0, 0], [0, 0, -1.0], [0, -1.0, 0]]),
    "FFP": np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]]),
}
#: Rotation directions of a control point (towards the next one), as in DICOM RT Plan.
ROTATIONS = ("CW", "CC", "NONE")
#: Sense (+1: the angle grows) of a CW turn of the gantry, the collimator and the couch.
CW_SENSE = {"gantry": 1.0, "collimator": 1.0, "couch": -1.0}
#: Smallest source–axis distance accepted [mm] (linacs: 800–1000 mm; Co-60 units 800 mm): a
#: smaller one is a unit slip (sad_mm = 100 meant as cm) or a typo.
MIN_SAD_MM = 500.0
#: Widest sweep [deg] of the gantry, collimator or couch within one beam (a C-arm linac's gantry
#: range is ±185° about 180°, IEC 61217 extended range); beyond it a plan is refused.
MAX_SWEEP_DEG = 370.0
#: MLC leaf travel directions: "X" (MLCX) or "Y" (MLCY) of the beam limiting device system.
MLC_AXES = ("X", "Y")
#: Delivery keys of a plan.toml linac beam (the machine's limits, :mod:`tetdose.plan.delivery`).
MACHINE_KEYS = ("dose_rate_mu_per_min", "max_gantry_deg_per_s", "max_leaf_mm_per_s",
                "beam_gap_s")


def _rot_y(deg: float) -> FloatArray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rot_z(deg: float) -> FloatArray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def support_to_patient(patient_position: str) -> FloatArray:
    """(3, 3) P: a vector's patient-frame components are P @ (its patient support components)."""
    if patient_position not in _PATIENT_TO_S:
        raise PlanError(f"patient position {patient_position!r} is unknown; use one of "
                        f"{PATIENT_POSITIONS}")
    return _PATIENT_TO_S[patient_position].copy()


def beam_axes(gantry_deg: float, collimator_deg: float, couch_deg: float,
              patient_position: str = "HFS") -> FloatArray:
    """(3, 3) rows X_b, Y_b, Z_b (unit vectors) in the DICOM patient frame.

    The beam travels along −Z_b; the source is at isocentre + SAD·Z_b.
    """
    p = support_to_patient(patient_position)
    b_in_f = _rot_y(gantry_deg) @ _rot_z(collimator_deg)  # columns: X_b, Y_b, Z_b in f
    b_in_s = _rot_z(couch_deg).T @ b_in_f  # f → s: s = R_z(couch)·f
    # patient → s is P (rows: patient axes in s), so s → patient is P^T's inverse = P.
    return (p @ b_in_s).T


def rotation_deg(start_deg: float, stop_deg: float, direction: str, sense: float = 1.0) -> float:
    """Signed turn [deg] from ``start_deg`` to ``stop_deg`` in ``direction`` (CW, CC, NONE).

    ``sense`` = +1 if a CW turn increases the angle (gantry, collimator), −1 if it decreases it
    (couch, seen from above). CW/CC: the turn of (0, 360] degrees in that sense, equal angles
    being a full turn (DICOM C.8.8.14.8); NONE: 0 for equal angles, else the shorter turn."""
    d = (float(stop_deg) - float(start_deg)) % 360.0
    if direction == "NONE":
        if min(d, 360.0 - d) < 1e-9:
            return 0.0
        if abs(d - 180.0) < 1e-9:
            raise PlanError(f"a turn from {start_deg:g}° to {stop_deg:g}° without a rotation "
                            "direction is ambiguous (180°): give CW or CC")
        return d if d < 180.0 else d - 360.0
    if direction not in ("CW", "CC"):
        raise PlanError(f"rotation direction {direction!r} is unknown; use one of {ROTATIONS}")
    up = (direction == "CW") == (sense > 0)  # does the angle grow?
    turn = d if up else (360.0 - d) % 360.0
    turn = 360.0 if turn < 1e-9 or turn > 360.0 - 1e-9 else turn
    return turn if up else -turn


@dataclass(frozen=True)
class MLC:
    """A multileaf collimator: N leaf pairs between ``boundaries_mm`` (N + 1, across the leaf
    travel) and ``positions_mm`` (2N: leaves 1..N of bank 1 (negative side), then N of bank 2,
    as in RT Plan); ``axis`` "X" (MLCX: leaves travel along X_b) or "Y" (MLCY)."""

    boundaries_mm: Sequence[float]
    positions_mm: Sequence[float]
    axis: str = "X"

    def __post_init__(self) -> None:
        b = np.asarray(self.boundaries_mm, dtype=np.float64).reshape(-1)
        p = np.asarray(self.positions_mm, dtype=np.float64).reshape(-1)
        if len(b) < 2 or np.any(np.diff(b) <= 0) or not np.all(np.isfinite(b)):
            raise PlanError("mlc boundaries_mm must be N + 1 increasing leaf edges")
        if len(p) != 2 * (len(b) - 1) or not np.all(np.isfinite(p)):
            raise PlanError(f"mlc positions_mm must hold 2N = {2 * (len(b) - 1)} values "
                            f"(bank 1, then bank 2), got {len(p)}")
        if np.any(p[: len(b) - 1] > p[len(b) - 1:]):
            raise PlanError("mlc leaves overlap: a bank-1 leaf lies beyond its bank-2 partner")
        if self.axis not in MLC_AXES:
            raise PlanError(f"mlc axis {self.axis!r} is unknown; use one of {MLC_AXES}")
        object.__setattr__(self, "boundaries_mm", b)
        object.__setattr__(self, "positions_mm", p)

    def moved(self, positions_mm: Sequence[float]) -> MLC:
        """The same leaves at ``positions_mm``."""
        return MLC(self.boundaries_mm, positions_mm, self.axis)

    def same_leaves(self, other: MLC) -> bool:
        """Same leaf layout (boundaries and travel axis)."""
        return (self.axis == other.axis and len(self.boundaries_mm) == len(other.boundaries_mm)
                and bool(np.all(self.boundaries_mm == other.boundaries_mm)))


def aperture_rectangles(jaws_mm: Sequence[float], mlc: MLC | None = None) -> FloatArray:
    """Open area on the isocentre plane as (R, 4) rectangles [x1, x2, y1, y2] [mm]: the jaws
    ``[x1, x2, y1, y2]`` intersected with each open leaf pair."""
    x1, x2, y1, y2 = (float(v) for v in jaws_mm)
    if mlc is None:
        rects = [[x1, x2, y1, y2]]
    else:
        b, p = np.asarray(mlc.boundaries_mm), np.asarray(mlc.positions_mm)
        n = len(b) - 1
        if mlc.axis == "X":
            rects = [[max(x1, p[i]), min(x2, p[n + i]), max(y1, b[i]), min(y2, b[i + 1])]
                     for i in range(n)]
        else:
            rects = [[max(x1, b[i]), min(x2, b[i + 1]), max(y1, p[i]), min(y2, p[n + i])]
                     for i in range(n)]
    out = np.array([r for r in rects if r[1] > r[0] and r[3] > r[2]], dtype=np.float64)
    return out.reshape(-1, 4)


#: Reference aperture: 100 × 100 mm² on the isocentre plane at SAD 1000 mm [mm², mm].
REFERENCE_FIELD_AREA_MM2 = 100.0 * 100.0
REFERENCE_SAD_MM = 1000.0


def fluence_weight(meterset: float, rects: FloatArray, sad_mm: float) -> float:
    """Source weight of a segment: ``meterset × (A / SAD²) / (A_ref / SAD_ref²)``.

    A is the open area of ``rects`` on the isocentre plane [mm²], so A/SAD² is (to first order)
    the aperture's solid angle; A_ref/SAD_ref² that of a 100 × 100 mm² field at 1000 mm. Photons
    are drawn in proportion to these weights, so every segment gets the same photons per MU per
    solid angle: the primary fluence per MU at the isocentre plane is the same for every field
    size (a linac's monitor chamber holds the fluence per MU, not the photons per MU, constant).
    A 100 × 100 mm² field at SAD 1000 mm has weight = meterset (MU)."""
    r = np.asarray(rects, dtype=np.float64).reshape(-1, 4)
    area = float(np.sum((r[:, 1] - r[:, 0]) * (r[:, 3] - r[:, 2])))
    return area_weight(meterset, area, sad_mm)


def area_weight(meterset: float, area_mm2: float, sad_mm: float) -> float:
    """``meterset × (A / SAD²) / (A_ref / SAD_ref²)`` for an open area A [mm²] (see
    :func:`fluence_weight`)."""
    return meterset * (area_mm2 / sad_mm**2) / (REFERENCE_FIELD_AREA_MM2 / REFERENCE_SAD_MM**2)


@dataclass(frozen=True, eq=False)
class ControlPoint:
    """One machine state of a beam: angles [deg], jaws [mm] at the isocentre plane, optional
    MLC, the cumulative meterset weight at this point (any unit: only differences relative to
    the beam's total count), the rotation directions towards the next control point (CW, CC,
    NONE) and an optional isocentre [mm] (None: the beam's)."""

    gantry_deg: float = 0.0
    collimator_deg: float = 0.0
    couch_deg: float = 0.0
    jaws_mm: Sequence[float] = (-50.0, 50.0, -50.0, 50.0)
    mlc: MLC | None = None
    meterset_weight: float = 0.0
    gantry_rotation: str = "NONE"
    collimator_rotation: str = "NONE"
    couch_rotation: str = "NONE"
    isocenter_mm: Sequence[float] | None = None

    def __post_init__(self) -> None:
        jaws = np.asarray(self.jaws_mm, dtype=np.float64).reshape(-1)
        if jaws.shape != (4,) or not np.all(np.isfinite(jaws)):
            raise PlanError(f"jaws_mm must be [x1, x2, y1, y2] in mm, got {self.jaws_mm!r}")
        if jaws[1] <= jaws[0] or jaws[3] <= jaws[2]:
            raise PlanError(f"jaws_mm = {jaws.tolist()} leave no opening; need x1 < x2, y1 < y2")
        angles = (self.gantry_deg, self.collimator_deg, self.couch_deg, self.meterset_weight)
        if not all(isinstance(a, int | float) and math.isfinite(a) for a in angles):
            raise PlanError(f"control point angles and meterset_weight must be finite numbers, "
                            f"got {angles}")
        for name in ("gantry_rotation", "collimator_rotation", "couch_rotation"):
            if getattr(self, name) not in ROTATIONS:
                raise PlanError(f"{name} {getattr(self, name)!r} is unknown; use one of "
                                f"{ROTATIONS}")
        if self.isocenter_mm is not None:
            iso = np.asarray(self.isocenter_mm, dtype=np.float64).reshape(-1)
            if iso.shape != (3,) or not np.all(np.isfinite(iso)):
                raise PlanError(f"isocenter_mm must be three numbers, got {self.isocenter_mm!r}")
            object.__setattr__(self, "isocenter_mm", iso)
        object.__setattr__(self, "jaws_mm", jaws)

    def turns_deg(self, nxt: ControlPoint) -> tuple[float, float, float]:
        """Signed gantry, collimator and couch turns [deg] from this control point to ``nxt``."""
        return (rotation_deg(self.gantry_deg, nxt.gantry_deg, self.gantry_rotation,
                             CW_SENSE["gantry"]),
                rotation_deg(self.collimator_deg, nxt.collimator_deg, self.collimator_rotation,
                             CW_SENSE["collimator"]),
                rotation_deg(self.couch_deg, nxt.couch_deg, self.couch_rotation,
                             CW_SENSE["couch"]))


@dataclass(frozen=True, eq=False)
class LinacBeam:
    """A treatment beam: quality, isocentre [mm, DICOM patient frame], its control points, SAD
    [mm], patient position, beam meterset (MU or relative) and the fluence mode (STANDARD or a
    flattening-filter-free "FFF" beam, computed with the same spectrum and a flat fluence).

    One control point is a static field delivering the whole meterset; two or more are a
    delivery in the sense of DICOM RT Plan: control point k → k+1 delivers the fraction
    (W_{k+1} − W_k)/(W_last − W_0) of the meterset while the machine moves linearly."""

    name: str
    spectrum: str
    isocenter_mm: Sequence[float]
    control_points: tuple[ControlPoint, ...]
    sad_mm: float = 1000.0
    patient_position: str = "HFS"
    meterset: float = 1.0
    isocenter_region: str | None = None
    fluence_mode: str = "STANDARD"
    #: Delivery limits of :data:`MACHINE_KEYS` given for this beam (:mod:`tetdose.plan.delivery`).
    machine: Mapping[str, float] = field(default_factory=dict)
    energies_mev: FloatArray = field(init=False, repr=False)
    line_weights: FloatArray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        from tetdose.plan.spectra import is_named, named_spectrum, read_spectrum

        iso = np.asarray(self.isocenter_mm, dtype=np.float64).reshape(-1)
        if iso.shape != (3,) or not np.all(np.isfinite(iso)):
            raise PlanError(f"isocenter_mm must be three numbers, got {self.isocenter_mm!r}")
        if not (math.isfinite(self.sad_mm) and self.sad_mm >= MIN_SAD_MM):
            raise PlanError(f"beam {self.name!r}: sad_mm = {self.sad_mm:g} mm is below "
                            f"{MIN_SAD_MM:g} mm (a linac's source–axis distance is 800–1000 mm; "
                            "give it in mm, e.g. sad_mm = 1000)")
        if self.patient_position not in PATIENT_POSITIONS:
            raise PlanError(f"[patient] position {self.patient_position!r} is unknown; use one "
                            f"of {PATIENT_POSITIONS}")
        if not (math.isfinite(self.meterset) and self.meterset > 0.0):
            raise PlanError(f"beam {self.name!r}: meterset must be positive, got {self.meterset}")
        cps = tuple(self.control_points)
        self._check_control_points(cps)
        e, w = (named_spectrum(self.spectrum) if is_named(self.spectrum)
                else read_spectrum(Path(self.spectrum)))
        for k, v in (("isocenter_mm", iso), ("control_points", cps), ("energies_mev", e),
                     ("line_weights", w)):
            object.__setattr__(self, k, v)

    def _check_control_points(self, cps: tuple[ControlPoint, ...]) -> None:
        where = f"beam {self.name!r}"
        if not cps or not all(isinstance(c, ControlPoint) for c in cps):
            raise PlanError(f"{where}: give at least one ControlPoint")
        if len(cps) > 1:
            w = np.array([c.meterset_weight for c in cps])
            if np.any(np.diff(w) < 0.0):
                k = int(np.argmax(np.diff(w) < 0.0)) + 1
                raise PlanError(f"{where}: control point {k} meterset weight {w[k]:g} is below "
                                f"the one before ({w[k - 1]:g}); weights are cumulative")
            if not w[-1] > w[0]:
                raise PlanError(f"{where} delivers no meterset: the cumulative meterset weight "
                                "does not grow between its first and last control point")
        self._check_turns(cps)
        mlcs = [c.mlc for c in cps]
        if any(m is None for m in mlcs) and any(m is not None for m in mlcs):
            raise PlanError(f"{where}: give every control point an MLC or none")
        if mlcs[0] is not None and not all(m.same_leaves(mlcs[0]) for m in mlcs):
            raise PlanError(f"{where}: every control point needs the same MLC leaf boundaries "
                            "and axis")

    def _check_turns(self, cps: tuple[ControlPoint, ...]) -> None:
        """Refuse a gantry, collimator or couch that sweeps more than :data:`MAX_SWEEP_DEG`."""
        if len(cps) < 2:
            return
        turns = np.array([a.turns_deg(b) for a, b in zip(cps[:-1], cps[1:], strict=True)])
        reach = np.concatenate([np.zeros((1, 3)), np.cumsum(turns, axis=0)])
        sweep = reach.max(axis=0) - reach.min(axis=0)
        for axis, deg in zip(("gantry", "collimator", "couch"), sweep, strict=True):
            if deg > MAX_SWEEP_DEG + 1e-6:
                raise PlanError(
                    f"beam {self.name!r}: its control points turn the {axis} through {deg:g}° "
                    f"one way, more than a linac can ({MAX_SWEEP_DEG:g}°); equal angles with "
                    f"direction CW or CC are a full turn each (DICOM C.8.8.14.8): give direction "
                    f"NONE where the {axis} stands still")

    @property
    def is_static(self) -> bool:
        """True if nothing but the meterset changes between the control points."""
        return all(same_state(a, b) for a, b in zip(self.control_points[:-1],
                                                      self.control_points[1:], strict=True))

    def isocenter_at(self, cp: ControlPoint) -> FloatArray:
        """The isocentre [mm] of control point ``cp`` (the beam's unless it gives one)."""
        return np.asarray(self.isocenter_mm if cp.isocenter_mm is None else cp.isocenter_mm,
                          dtype=np.float64)


def same_state(a: ControlPoint, b: ControlPoint) -> bool:
    """True if control points ``a`` and ``b`` hold the same jaws, leaves, isocentre and angles
    with no turn between them (a static segment a → b)."""
    same_mlc = (a.mlc is None) == (b.mlc is None) and (
        a.mlc is None or bool(np.all(a.mlc.positions_mm == b.mlc.positions_mm)))
    iso_a = None if a.isocenter_mm is None else np.asarray(a.isocenter_mm).tolist()
    iso_b = None if b.isocenter_mm is None else np.asarray(b.isocenter_mm).tolist()
    return (bool(np.all(a.jaws_mm == b.jaws_mm)) and same_mlc and iso_a == iso_b
            and a.turns_deg(b) == (0.0, 0.0, 0.0))


_LINAC_KEYS = {"type", "name", "spectrum", "isocenter_mm", "isocenter", "gantry_deg",
               "collimator_deg", "couch_deg", "sad_mm", "jaws_mm", "mlc", "weight",
               "control_points", "arc", "fluence_mode", *MACHINE_KEYS}
_CP_KEYS = {"gantry_deg", "collimator_deg", "couch_deg", "jaws_mm", "mlc", "meterset_weight",
            "gantry_direction", "collimator_direction", "couch_direction", "isocenter_mm"}
_ARC_KEYS = {"start_deg", "stop_deg", "direction"}


def linac_beam_from_dict(d: Mapping[str, Any], i: int, patient_position: str,
                         base_dir: Path = Path(".")) -> LinacBeam:
    """A ``type = "linac"`` table of plan.toml (see :mod:`tetdose.plan.model`); a spectrum
    that is not a named beam quality is a CSV file (energy_mev, weight) relative to
    ``base_dir`` (the plan file's folder).

    The beam's ``gantry_deg``, ``collimator_deg``, ``couch_deg``, ``jaws_mm`` and ``mlc`` are
    its first machine state. ``control_points = [{meterset_weight, gantry_deg, jaws_mm, mlc,
    gantry_direction, …}, …]``: each control point changes what it names and keeps the rest
    (as in DICOM: an angle the next control point does not name does not turn, whatever the
    direction); ``mlc`` there is the list of 2N leaf positions (the beam's ``mlc`` table
    gives ``boundaries_mm`` and ``axis``). ``arc = {start_deg, stop_deg, direction}``: a
    rotation from start to stop (CW or CC; start = stop is a full turn) at the beam's aperture.
    """
    from tetdose.plan.spectra import is_named

    where = f"beam {i + 1}"
    unknown = set(d) - _LINAC_KEYS
    if unknown:
        raise PlanError(f"{where}: unknown key(s) {sorted(unknown)}; allowed for linac beams: "
                        f"{sorted(_LINAC_KEYS)}")
    if ("isocenter_mm" in d) == ("isocenter" in d):
        raise PlanError(f"{where}: give exactly one of isocenter_mm = [x, y, z] or "
                        "isocenter = \"structure\"")
    if "spectrum" not in d:
        raise PlanError(f"{where}: a linac beam needs spectrum = \"6MV\" (or 10MV, 15MV, Co60, "
                        "Co60scatter, or a spectrum.csv)")
    if "arc" in d and ("control_points" in d or "gantry_deg" in d):
        raise PlanError(f"{where}: give arc = {{start_deg, stop_deg, direction}} alone, without "
                        "gantry_deg or control_points")
    spectrum = str(d["spectrum"])
    if not is_named(spectrum):
        spectrum = str(base_dir / spectrum)
    try:
        cps = _control_points_from_dict(d, where)
        region = d.get("isocenter")
        return LinacBeam(str(d.get("name", f"beam{i + 1}")), spectrum,
                         d.get("isocenter_mm", (0.0, 0.0, 0.0)), cps,
                         float(d.get("sad_mm", 1000.0)), patient_position,
                         float(d.get("weight", 1.0)),
                         None if region is None else str(region),
                         str(d.get("fluence_mode", "STANDARD")), _machine(d))
    except (KeyError, TypeError, ValueError) as exc:
        raise PlanError(f"{where}: malformed linac beam ({exc}); mlc needs boundaries_mm and "
                        "positions_mm, control points need meterset_weight") from None
    except PlanError as exc:
        raise PlanError(f"{where}: {exc}") from None


def _machine(d: Mapping[str, Any]) -> dict[str, float]:
    """The delivery limits of :data:`MACHINE_KEYS` a linac table gives (positive numbers; the
    gap between beams may be 0)."""
    out = {}
    for key in MACHINE_KEYS:
        if key not in d:
            continue
        v = d[key]
        ok = isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
        if not ok or v < 0.0 or (v == 0.0 and key != "beam_gap_s"):
            raise PlanError(f"{key} = {v!r} must be a positive number (beam_gap_s may be 0)")
        out[key] = float(v)
    return out


def _control_points_from_dict(d: Mapping[str, Any], where: str) -> tuple[ControlPoint, ...]:
    """The control points of a plan.toml linac table (see :func:`linac_beam_from_dict`)."""
    mlc_d = d.get("mlc")
    mlc = None
    if mlc_d is not None:
        n = len(mlc_d["boundaries_mm"]) - 1
        mlc = MLC(mlc_d["boundaries_mm"], mlc_d.get("positions_mm", [0.0] * (2 * n)),
                  str(mlc_d.get("axis", "X")))
    state: dict[str, Any] = {
        "gantry_deg": float(d.get("gantry_deg", 0.0)),
        "collimator_deg": float(d.get("collimator_deg", 0.0)),
        "couch_deg": float(d.get("couch_deg", 0.0)),
        "jaws_mm": d.get("jaws_mm", (-50.0, 50.0, -50.0, 50.0)), "mlc": mlc,
        "meterset_weight": 0.0, "gantry_rotation": "NONE", "collimator_rotation": "NONE",
        "couch_rotation": "NONE", "isocenter_mm": None}
    if "arc" in d:
        arc = d["arc"]
        unknown = set(arc) - _ARC_KEYS
        if unknown or not {"start_deg", "stop_deg", "direction"} <= set(arc):
            raise PlanError(f"arc = {dict(arc)} needs exactly start_deg, stop_deg and "
                            "direction = \"CW\" | \"CC\"")
        if arc["direction"] not in ("CW", "CC"):
            raise PlanError(f"arc direction {arc['direction']!r} must be \"CW\" or \"CC\"")
        return (ControlPoint(**dict(state, gantry_deg=float(arc["start_deg"]),
                                    gantry_rotation=str(arc["direction"]))),
                ControlPoint(**dict(state, gantry_deg=float(arc["stop_deg"]),
                                    meterset_weight=1.0)))
    if "control_points" not in d:
        return (ControlPoint(**state),)
    items = d["control_points"]
    if not isinstance(items, list) or not items:
        raise PlanError("control_points must be a non-empty list of tables")
    out = []
    for k, cp in enumerate(items):
        unknown = set(cp) - _CP_KEYS
        if unknown:
            raise PlanError(f"control point {k}: unknown key(s) {sorted(unknown)}; allowed: "
                            f"{sorted(_CP_KEYS)}")
        if "meterset_weight" not in cp:
            raise PlanError(f"control point {k} needs meterset_weight (cumulative)")
        for key in ("gantry_deg", "collimator_deg", "couch_deg", "meterset_weight"):
            if key in cp:
                state[key] = float(cp[key])
        for key in ("gantry", "collimator", "couch"):
            if f"{key}_direction" in cp:
                state[f"{key}_rotation"] = str(cp[f"{key}_direction"])
        for key in ("jaws_mm", "isocenter_mm"):
            if key in cp:
                state[key] = cp[key]
        if "mlc" in cp:
            if state["mlc"] is None:
                raise PlanError(f"control point {k} gives mlc leaf positions but the beam has "
                                "no mlc = {boundaries_mm = [...]} table")
            state["mlc"] = state["mlc"].moved(cp["mlc"])
        # An angle the next control point omits is unchanged: no turn towards it.
        still = {f"{key}_rotation": "NONE" for key in ("gantry", "collimator", "couch")
                 if k + 1 < len(items) and f"{key}_deg" not in items[k + 1]}
        try:
            out.append(ControlPoint(**dict(state, **still)))
        except PlanError as exc:
            raise PlanError(f"control point {k}: {exc}") from None
    return tuple(out)
