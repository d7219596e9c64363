"""One photon source (beam) of a plan: kind, position [mm], direction, spectrum lines [MeV],
field, weight; validated on construction (errors are :class:`~tetdose.errors.PlanError`).

The plan file format and the field axes ``e1``, ``e2`` are described in
:mod:`tetdose.plan.model`; treatment (linac) beams (:mod:`tetdose.plan.beams`) expand
into sources of kind "linac", one per open segment.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from tetdose._typing import FloatArray
from tetdose.errors import PlanError

#: The one spelling of each source kind (plan.toml ``type``).
SOURCE_KINDS = ("pencil", "parallel", "point", "linac")
#: The particles a source may emit (plan.toml ``particle``; electrons and positrons need
#: physics "dose").
PARTICLES = ("photon", "electron", "positron")


def _unit(vec: Sequence[float], what: str) -> FloatArray:
    arr = np.asarray(vec, dtype=np.float64).reshape(-1)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise PlanError(f"{what} must be three finite numbers, got {vec!r}")
    norm = float(np.linalg.norm(arr))
    if norm == 0.0:
        raise PlanError(f"{what} must not be the zero vector")
    return arr / norm


@dataclass(frozen=True, eq=False)
class PhotonSource:
    """One beam: where photons start [mm], where they go, their energies [MeV] and weight.

    ``energies_mev``/``line_weights`` are discrete spectrum lines (one line: mono-energetic),
    kinetic energies for electrons and positrons (``particle``, default photons).
    """

    kind: str
    position_mm: Sequence[float]
    direction: Sequence[float] = (0.0, 0.0, 1.0)
    energies_mev: Sequence[float] = (1.0,)
    line_weights: Sequence[float] = (1.0,)
    field_mm: Sequence[float] = (0.0, 0.0)
    half_angle_deg: float = 180.0
    weight: float = 1.0
    field_x_direction: Sequence[float] | None = None
    sad_mm: float = 0.0
    aperture_mm: FloatArray | None = None
    particle: str = "photon"
    e1: FloatArray = field(init=False, repr=False)
    e2: FloatArray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if self.kind not in SOURCE_KINDS:
            raise PlanError(f"beam type {self.kind!r} is unknown; use one of {SOURCE_KINDS}")
        if self.particle not in PARTICLES:
            raise PlanError(f"beam particle {self.particle!r} is unknown; use one of {PARTICLES}")
        pos = np.asarray(self.position_mm, dtype=np.float64).reshape(-1)
        if pos.shape != (3,) or not np.all(np.isfinite(pos)):
            raise PlanError(f"beam position_mm must be three finite numbers, got {pos}")
        axis = _unit(self.direction, "beam direction")
        e = np.asarray(self.energies_mev, dtype=np.float64).reshape(-1)
        wl = np.asarray(self.line_weights, dtype=np.float64).reshape(-1)
        if len(e) == 0 or len(e) != len(wl):
            raise PlanError("a beam needs at least one energy and one weight per energy")
        if not np.all(np.isfinite(e)) or np.any(e <= 0.0):
            raise PlanError(f"beam energies must be positive MeV, got {e.tolist()}")
        if not np.all(np.isfinite(wl)) or np.any(wl < 0.0) or wl.sum() <= 0.0:
            raise PlanError("spectrum weights must be non-negative with a positive sum")
        fld = np.asarray(self.field_mm, dtype=np.float64).reshape(-1)
        if fld.shape != (2,) or np.any(fld < 0.0) or not np.all(np.isfinite(fld)):
            raise PlanError(f"field_mm must be two non-negative sizes, got {self.field_mm}")
        if self.kind == "parallel" and np.any(fld <= 0.0):
            raise PlanError("a parallel beam needs a positive field_mm = [x, y]")
        if not 0.0 < float(self.half_angle_deg) <= 180.0:
            raise PlanError(f"half_angle_deg must lie in (0, 180], got {self.half_angle_deg}")
        if not (math.isfinite(self.weight) and self.weight > 0.0):
            raise PlanError(f"beam weight must be positive, got {self.weight}")
        ref = (np.eye(3)[int(np.argmin(np.abs(axis)))] if self.field_x_direction is None
               else _unit(self.field_x_direction, "field_x_direction"))
        e1 = ref - np.dot(ref, axis) * axis
        if np.linalg.norm(e1) < 1e-9:
            raise PlanError("field_x_direction must not be parallel to the beam direction")
        for name, val in (("position_mm", pos), ("direction", axis), ("energies_mev", e),
                          ("line_weights", wl), ("field_mm", fld)):
            object.__setattr__(self, name, val)
        object.__setattr__(self, "e1", e1 / np.linalg.norm(e1))
        if self.kind == "linac":
            # IEC 61217 beam limiting device frame: X_b = e1, Y_b = e2, beam along −Z_b.
            object.__setattr__(self, "e2", np.cross(self.e1, axis))
            rects = np.asarray(self.aperture_mm if self.aperture_mm is not None else
                               np.zeros((0, 4)), dtype=np.float64).reshape(-1, 4)
            if (len(rects) == 0 or np.any(rects[:, 1] <= rects[:, 0])
                    or np.any(rects[:, 3] <= rects[:, 2]) or not self.sad_mm > 0.0):
                raise PlanError("a linac source needs sad_mm > 0 and open aperture rectangles "
                                "[x1, x2, y1, y2]")
            object.__setattr__(self, "aperture_mm", rects)
        else:
            object.__setattr__(self, "e2", np.cross(axis, self.e1))

    @property
    def mean_energy_mev(self) -> float:
        w = np.asarray(self.line_weights)
        return float(np.dot(w, self.energies_mev) / w.sum())


def check_source_keys(d: Mapping[str, Any], allowed: set[str], where: str) -> None:
    """PlanError unless the ``[[beam]]`` table ``d`` uses only ``allowed`` keys and gives exactly
    one of ``energy_mev`` and ``spectrum``."""
    unknown = set(d) - allowed
    if unknown:
        raise PlanError(f"{where}: unknown key(s) {sorted(unknown)}; allowed: {sorted(allowed)}")
    if ("energy_mev" in d) == ("spectrum" in d):
        raise PlanError(f"{where}: give exactly one of energy_mev or spectrum")
