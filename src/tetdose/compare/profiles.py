"""Dose profiles along a straight line through a mesh dose and through a voxel dose.

The line runs from ``start_mm`` to ``end_mm`` with ``n`` equally spaced sample points
p_i = start + i/(n−1)·(end − start). The mesh dose is piecewise constant per tetrahedron (the
value of the tet containing p_i, located by barycentric coordinates; NaN outside the mesh); the
image dose is trilinear between voxel centres (NaN beyond the image's outer faces).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tetdose._typing import FloatArray
from tetdose.core.image import Image
from tetdose.core.mesh import TetMesh
from tetdose.core.transfer import interpolate_at_points, locate_points, per_tet_dose
from tetdose.errors import OptionError


@dataclass(frozen=True, eq=False)
class Profile:
    """Samples along a line: distance from the start [mm], points [mm], dose [Gy]."""

    distance_mm: FloatArray
    points_mm: FloatArray
    dose_gy: FloatArray
    label: str = ""


def line_points(start_mm: FloatArray, end_mm: FloatArray, n: int) -> tuple[FloatArray, FloatArray]:
    """(n, 3) equally spaced points from start to end [mm] and their distances from start."""
    if n < 2:
        raise OptionError(f"a profile needs n ≥ 2 points, got {n}; use e.g. n=200")
    a = np.asarray(start_mm, dtype=np.float64).reshape(3)
    b = np.asarray(end_mm, dtype=np.float64).reshape(3)
    t = np.linspace(0.0, 1.0, n)
    return a + t[:, None] * (b - a), t * float(np.linalg.norm(b - a))


def mesh_profile(mesh: TetMesh, dose_gy: FloatArray, start_mm: FloatArray, end_mm: FloatArray,
                 n: int = 200, *, label: str = "mesh") -> Profile:
    """Profile of a per-tet dose (piecewise constant; NaN outside the mesh)."""
    dose = per_tet_dose(mesh, dose_gy)
    pts, dist = line_points(start_mm, end_mm, n)
    tet, _ = locate_points(mesh, pts)
    values = np.where(tet >= 0, dose[np.maximum(tet, 0)], np.nan)
    return Profile(dist, pts, values, label)


def image_profile(image: Image, start_mm: FloatArray, end_mm: FloatArray, n: int = 200, *,
                  label: str = "voxel") -> Profile:
    """Profile of a voxel dose (trilinear; NaN outside the image)."""
    pts, dist = line_points(start_mm, end_mm, n)
    return Profile(dist, pts, interpolate_at_points(image, pts), label)
