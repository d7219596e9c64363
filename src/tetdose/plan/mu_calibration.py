"""Absolute dose per monitor unit: ``[calibration] gy_per_mu`` scales doses per source photon
to Gy per fraction from the plan's meterset (MU).

Reference conditions (the user's machine calibration is stated in them): a water phantom
300 × 300 mm² wide and ≥ 300 mm deep, SSD ``ssd_mm`` (default 1000 mm), a 100 × 100 mm² field
on the isocentre plane at SAD 1000 mm, the reference point on the central axis at depth
``depth_mm`` (default 100 mm). ``gy_per_mu`` is the absorbed dose to water there per MU.

:mod:`tetdose.dose.absolute` computes, with the plan's beam quality and the same engine, the dose
per source photon D_ref at that point (kerma in a 20 × 20 mm² voxel, ``depth_mm`` at its centre, track-length
estimator). Linac sources carry the weight W = MU × (A/SAD²)/(A_ref/SAD_ref²)
(:func:`tetdose.plan.beams.fluence_weight`: equal fluence per MU for every aperture), so a
plan with total weight ΣW delivers N = gy_per_mu · ΣW / D_ref source photons per fraction and

    D(x) [Gy per fraction] = gy_per_mu · ΣW · D(x)_per photon / D_ref.

For one 100 × 100 mm² beam of M MU in the reference conditions this is D(ref) = gy_per_mu · M
(the test checks it). Limits: no head-scatter / output-factor model (S_c = 1 for every field,
so fields far from 100 × 100 mm² are off by their S_c, a few %), no monitor back-scatter, one
beam quality per plan, kerma (not dose) in the build-up region, so ``depth_mm`` must lie beyond
d_max. A plan gives either a prescription or a calibration, not both.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from tetdose.errors import PlanError

#: Label of MU-calibrated doses (plots, files, records).
MU_UNIT = "Gy per fraction"
_KEYS = {"gy_per_mu", "depth_mm", "ssd_mm", "reference_histories"}
#: Reference field: 100 × 100 mm² on the isocentre plane at SAD 1000 mm.
REFERENCE_JAWS_MM = (-50.0, 50.0, -50.0, 50.0)
REFERENCE_SAD_MM = 1000.0
#: Water phantom of the reference computation: width, minimal depth, scoring voxel width [mm].
_PHANTOM_WIDTH_MM, _PHANTOM_DEPTH_MM, _VOXEL_WIDTH_MM = 300.0, 300.0, 20.0


@dataclass(frozen=True)
class MUCalibration:
    """``gy_per_mu`` [Gy/MU] at ``depth_mm`` on the axis, SSD ``ssd_mm``, 100 × 100 mm²."""

    gy_per_mu: float
    depth_mm: float = 100.0
    ssd_mm: float = 1000.0
    reference_histories: int = 1_000_000

    def __post_init__(self) -> None:
        if not (math.isfinite(self.gy_per_mu) and self.gy_per_mu > 0):
            raise PlanError(f"[calibration] gy_per_mu must be positive, got {self.gy_per_mu}")
        if not 0.0 < self.depth_mm <= 200.0:
            raise PlanError(f"[calibration] depth_mm must lie in (0, 200] mm, got {self.depth_mm}")
        if not 500.0 <= self.ssd_mm <= 1500.0:
            raise PlanError(f"[calibration] ssd_mm must lie in [500, 1500] mm, got {self.ssd_mm}")
        if int(self.reference_histories) < 10_000:
            raise PlanError("[calibration] reference_histories must be at least 10000")

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> MUCalibration:
        unknown = set(d) - _KEYS
        if unknown or "gy_per_mu" not in d:
            raise PlanError(f"[calibration] needs gy_per_mu (optional depth_mm, ssd_mm, "
                            f"reference_histories); unknown: {sorted(unknown)}")
        return cls(float(d["gy_per_mu"]), float(d.get("depth_mm", 100.0)),
                   float(d.get("ssd_mm", 1000.0)),
                   int(d.get("reference_histories", 1_000_000)))


def reference_phantom(depth_mm: float) -> tuple[Any, Any, int]:
    """(density, labels, flat index of the reference voxel) of the reference water phantom:
    surface at y = 0, depth along +y, voxels ``_VOXEL_WIDTH_MM`` wide laterally and about
    10 mm thick, the reference voxel centred on the axis at ``depth_mm``."""
    from tetdose.core.image import Image, ImageGrid

    above = max(int(round(depth_mm / 10.0 - 0.5)), 0)
    dz = depth_mm / (above + 0.5)
    ny = int(math.ceil(_PHANTOM_DEPTH_MM / dz))
    nl = int(round(_PHANTOM_WIDTH_MM / _VOXEL_WIDTH_MM)) | 1  # odd: a voxel on the axis
    half = (nl - 1) / 2 * _VOXEL_WIDTH_MM
    grid = ImageGrid(np.array([-half, dz / 2, -half]), np.array([_VOXEL_WIDTH_MM, dz,
                                                                  _VOXEL_WIDTH_MM]),
                     np.eye(3), (nl, ny, nl))
    index = int(np.ravel_multi_index((nl // 2, above, nl // 2), grid.shape))
    return (Image(np.ones(grid.shape), grid), Image(np.ones(grid.shape, dtype=np.int16), grid),
            index)
