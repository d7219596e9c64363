"""Linac treatment beams: IEC 61217 gantry/collimator/couch angles → DICOM patient frame.

Coordinate systems (IEC 61217, all rotations right-handed about their axis, i.e. clockwise seen
from the origin looking along the positive axis):

- Fixed system f: X_f to the right of an observer at the couch foot facing the gantry, Y_f from
  the isocentre towards the gantry, Z_f up. Gantry system g = R_y(gantry)·f: the source sits at
  +SAD·Z_g, so at gantry 0 it is above the isocentre and at gantry 90 on the +X_f side.
- Beam limiting device system b = R_z(collimator)·g: the X jaws (X1 negative, X2 positive) and
  MLCX leaves move along X_b, the Y jaws along Y_b. Aperture coordinates are in mm projected to
  the isocentre plane, as in DICOM RT Plan.
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
from tetdose.plan.photon_source import PhotonSource

PATIENT_POSITIONS = ("HFS", "HFP", "FFS", "FFP")
#: Rows: DICOM patient axes (x, y, z) expressed in the patient support system s.
_PATIENT_TO_S = {
    "HFS": np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]]),
    "HFP": np.array([[-1.0, 0, 0], [0, 0, 1.0], [0, 1.0, 0]]),
    "FFS": np.array([[-1.0, 0, 0], [0, 0, -1.0], [0, -1.0, 0]]),
    "FFP": np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]]),
}


def _rot_y(deg: float) -> FloatArray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rot_z(deg: float) -> FloatArray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def beam_axes(gantry_deg: float, collimator_deg: float, couch_deg: float,
              patient_position: str = "HFS") -> FloatArray:
    """(3, 3) rows X_b, Y_b, Z_b (unit vectors) in the DICOM patient frame.

    The beam travels along −Z_b; the source is at isocentre + SAD·Z_b.
    """
    if patient_position not in _PATIENT_TO_S:
        raise PlanError(f"patient position {patient_position!r} is unknown; use one of "
                        f"{PATIENT_POSITIONS}")
    b_in_f = _rot_y(gantry_deg) @ _rot_z(collimator_deg)  # columns: X_b, Y_b, Z_b in f
    b_in_s = _rot_z(couch_deg).T @ b_in_f  # f → s: s = R_z(couch)·f
    # patient → s is P (rows: patient axes in s), so s → patient is P^T's inverse = P.
    return (_PATIENT_TO_S[patient_position] @ b_in_s).T


@dataclass(frozen=True)
class MLC:
    """An MLCX bank: N leaf pairs between ``boundaries_mm`` (N + 1, along Y_b) and
    ``positions_mm`` (2N: leaves 1..N on the X1 side, then N on the X2 side, as in RT Plan)."""

    boundaries_mm: Sequence[float]
    positions_mm: Sequence[float]

    def __post_init__(self) -> None:
        b = np.asarray(self.boundaries_mm, dtype=np.float64).reshape(-1)
        p = np.asarray(self.positions_mm, dtype=np.float64).reshape(-1)
        if len(b) < 2 or np.any(np.diff(b) <= 0):
            raise PlanError("mlc boundaries_mm must be N + 1 increasing leaf edges")
        if len(p) != 2 * (len(b) - 1):
            raise PlanError(f"mlc positions_mm must hold 2N = {2 * (len(b) - 1)} values "
                            f"(X1 bank, then X2 bank), got {len(p)}")
        if np.any(p[: len(b) - 1] > p[len(b) - 1:]):
            raise PlanError("mlc leaves overlap: an X1 leaf lies beyond its X2 partner")
        object.__setattr__(self, "boundaries_mm", b)
        object.__setattr__(self, "positions_mm", p)


def aperture_rectangles(jaws_mm: Sequence[float], mlc: MLC | None = None) -> FloatArray:
    """Open area on the isocentre plane as (R, 4) rectangles [x1, x2, y1, y2] [mm]: the jaws
    ``[x1, x2, y1, y2]`` intersected with each open leaf pair."""
    x1, x2, y1, y2 = (float(v) for v in jaws_mm)
    if mlc is None:
        rects = [[x1, x2, y1, y2]]
    else:
        b, p = np.asarray(mlc.boundaries_mm), np.asarray(mlc.positions_mm)
        n = len(b) - 1
        rects = [[max(x1, p[i]), min(x2, p[n + i]), max(y1, b[i]), min(y2, b[i + 1])]
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
    return meterset * (area / sad_mm**2) / (REFERENCE_FIELD_AREA_MM2 / REFERENCE_SAD_MM**2)


@dataclass(frozen=True, eq=False)
class ControlPoint:
    """One static segment of a beam: angles [deg], jaws [mm] at the isocentre plane, optional
    MLC, and the fraction of the beam's meterset delivered in it."""

    gantry_deg: float = 0.0
    collimator_deg: float = 0.0
    couch_deg: float = 0.0
    jaws_mm: Sequence[float] = (-50.0, 50.0, -50.0, 50.0)
    mlc: MLC | None = None
    meterset_fraction: float = 1.0

    def __post_init__(self) -> None:
        jaws = np.asarray(self.jaws_mm, dtype=np.float64).reshape(-1)
        if jaws.shape != (4,) or not np.all(np.isfinite(jaws)):
            raise PlanError(f"jaws_mm must be [x1, x2, y1, y2] in mm, got {self.jaws_mm!r}")
        if jaws[1] <= jaws[0] or jaws[3] <= jaws[2]:
            raise PlanError(f"jaws_mm = {jaws.tolist()} leave no opening; need x1 < x2, y1 < y2")
        if not self.meterset_fraction >= 0.0:
            raise PlanError("a segment's meterset fraction must be ≥ 0")
        object.__setattr__(self, "jaws_mm", jaws)


@dataclass(frozen=True, eq=False)
class LinacBeam:
    """A treatment beam: quality, isocentre [mm, DICOM patient frame], SAD [mm], patient
    position, beam weight (meterset, MU or relative) and its segments."""

    name: str
    spectrum: str
    isocenter_mm: Sequence[float]
    segments: tuple[ControlPoint, ...]
    sad_mm: float = 1000.0
    patient_position: str = "HFS"
    meterset: float = 1.0
    isocenter_region: str | None = None
    energies_mev: FloatArray = field(init=False, repr=False)
    line_weights: FloatArray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        from tetdose.plan.spectra import is_named, named_spectrum, read_spectrum

        iso = np.asarray(self.isocenter_mm, dtype=np.float64).reshape(-1)
        if iso.shape != (3,) or not np.all(np.isfinite(iso)):
            raise PlanError(f"isocenter_mm must be three numbers, got {self.isocenter_mm!r}")
        if not self.sad_mm > 0.0:
            raise PlanError(f"sad_mm must be positive, got {self.sad_mm}")
        if self.patient_position not in PATIENT_POSITIONS:
            raise PlanError(f"[patient] position {self.patient_position!r} is unknown; use one "
                            f"of {PATIENT_POSITIONS}")
        segs = tuple(self.segments)
        if not segs or sum(s.meterset_fraction for s in segs) <= 0.0:
            raise PlanError(f"beam {self.name!r} delivers no meterset (no segment with weight)")
        if not (math.isfinite(self.meterset) and self.meterset > 0.0):
            raise PlanError(f"beam {self.name!r}: meterset must be positive, got {self.meterset}")
        e, w = (named_spectrum(self.spectrum) if is_named(self.spectrum)
                else read_spectrum(Path(self.spectrum)))
        for k, v in (("isocenter_mm", iso), ("segments", segs), ("energies_mev", e),
                     ("line_weights", w)):
            object.__setattr__(self, k, v)

    def sources(self) -> list:  # list[PhotonSource]
        """One point source per segment with an open aperture, weighted by its meterset times
        the solid angle of its aperture (see :func:`fluence_weight`): the same number of photons
        per MU and per unit of open area, so the fluence per MU on the isocentre plane is the
        same for every segment and beam (no output factor model)."""
        total = sum(s.meterset_fraction for s in self.segments)
        out = []
        for seg in self.segments:
            rects = aperture_rectangles(seg.jaws_mm, seg.mlc)
            if seg.meterset_fraction <= 0.0 or len(rects) == 0:
                continue
            mu = self.meterset * seg.meterset_fraction / total
            xb, _yb, zb = beam_axes(seg.gantry_deg, seg.collimator_deg, seg.couch_deg,
                                    self.patient_position)
            out.append(PhotonSource(
                "linac", self.isocenter_mm + self.sad_mm * zb, -zb,
                energies_mev=self.energies_mev, line_weights=self.line_weights,
                weight=fluence_weight(mu, rects, self.sad_mm), field_x_direction=xb,
                sad_mm=self.sad_mm, aperture_mm=rects))
        if not out:
            raise PlanError(f"beam {self.name!r}: every segment is closed (jaws ∩ MLC empty)")
        return out


_LINAC_KEYS = {"type", "name", "spectrum", "isocenter_mm", "isocenter", "gantry_deg",
               "collimator_deg", "couch_deg", "sad_mm", "jaws_mm", "mlc", "weight"}


def linac_beam_from_dict(d: Mapping[str, Any], i: int, patient_position: str,
                         base_dir: Path = Path(".")) -> LinacBeam:
    """A ``type = "linac"`` table of plan.toml (see :mod:`tetdose.plan.model`); a spectrum
    that is not a named beam quality is a CSV file (energy_mev, weight) relative to
    ``base_dir`` (the plan file's folder)."""
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
    spectrum = str(d["spectrum"])
    if not is_named(spectrum):
        spectrum = str(base_dir / spectrum)
    try:
        mlc = d.get("mlc")
        seg = ControlPoint(float(d.get("gantry_deg", 0.0)), float(d.get("collimator_deg", 0.0)),
                           float(d.get("couch_deg", 0.0)),
                           d.get("jaws_mm", (-50.0, 50.0, -50.0, 50.0)),
                           None if mlc is None else MLC(mlc["boundaries_mm"],
                                                        mlc["positions_mm"]))
        region = d.get("isocenter")
        return LinacBeam(str(d.get("name", f"beam{i + 1}")), spectrum,
                         d.get("isocenter_mm", (0.0, 0.0, 0.0)), (seg,),
                         float(d.get("sad_mm", 1000.0)), patient_position,
                         float(d.get("weight", 1.0)),
                         None if region is None else str(region))
    except (KeyError, TypeError) as exc:
        raise PlanError(f"{where}: malformed linac beam ({exc}); mlc needs boundaries_mm and "
                        "positions_mm") from None
    except PlanError as exc:
        raise PlanError(f"{where}: {exc}") from None
