"""Volumes of sublevel sets of piecewise-linear fields on a tetrahedral mesh, and the level shift
that gives a label its voxel volume.

For a linear f on a tetrahedron with vertex values sorted a ≤ b ≤ c ≤ d, the fraction of its
volume where f < t is the cumulative distribution of a linear form on the uniform simplex, a
cubic B-spline with knots a, b, c, d (Curry & Schoenberg 1966):

    F(t) = 0                                                      t ≤ a
         = (t−a)³ / ((b−a)(c−a)(d−a))                             a < t ≤ b
         = (t−a)³ / ((b−a)(c−a)(d−a)) − (t−b)³ / ((b−a)(c−b)(d−b))    b < t ≤ c
         = 1 − (d−t)³ / ((d−a)(d−b)(d−c))                         c < t < d
         = 1                                                      t ≥ d

Equal knots are separated by ``KNOT_GAP_MM`` first (the middle branch then loses at most
ε·|t−a|/gap ≈ 1e−10 to cancellation). A level-set mesher that splits the tetrahedra on the
zero set of φ makes the region {φ < 0} of this exact volume; :func:`volume_shift` finds the
constant δ for which {φ < δ} has the target (voxel) volume, by Newton steps on V(δ) whose slope
is the area of the level set (coarea formula), estimated by a central difference.
"""

from __future__ import annotations

import numpy as np

from tetdose._typing import FloatArray

#: Smallest separation [mm] of sorted vertex values (ties broken upwards).
KNOT_GAP_MM = 1e-6
#: Newton iterations and their relative volume tolerance.
MAX_ITER, VOLUME_RTOL = 8, 1e-4


def fraction_below(values: FloatArray, t: float) -> FloatArray:
    """Volume fraction of each tetrahedron (M,) where the linear field with vertex ``values``
    (M, 4) is below ``t`` (see the module docstring)."""
    v = np.sort(values, axis=1)
    for col in range(1, 4):
        v[:, col] = np.maximum(v[:, col], v[:, col - 1] + KNOT_GAP_MM)
    a, b, c, d = v.T
    out = np.zeros(len(v))
    out[t >= d] = 1.0
    m1 = (t > a) & (t <= b)
    out[m1] = ((t - a[m1]) ** 3 / ((b[m1] - a[m1]) * (c[m1] - a[m1]) * (d[m1] - a[m1])))
    m2 = (t > b) & (t <= c)
    a2, b2, c2, d2 = a[m2], b[m2], c[m2], d[m2]
    out[m2] = ((t - a2) ** 3 / ((b2 - a2) * (c2 - a2) * (d2 - a2))
               - (t - b2) ** 3 / ((b2 - a2) * (c2 - b2) * (d2 - b2)))
    m3 = (t > c) & (t < d)
    out[m3] = 1.0 - (d[m3] - t) ** 3 / ((d[m3] - a[m3]) * (d[m3] - b[m3]) * (d[m3] - c[m3]))
    return np.clip(out, 0.0, 1.0)


def volume_below(values: FloatArray, volumes_mm3: FloatArray, t: float) -> float:
    """Volume [mm³] of {f < t} for the piecewise-linear f with vertex ``values`` (M, 4)."""
    return float(volumes_mm3 @ fraction_below(values, t))


def volume_shift(values: FloatArray, volumes_mm3: FloatArray, target_mm3: float,
                 step_mm: float) -> float:
    """δ [mm] with volume({f < δ}) = ``target_mm3``, by Newton steps from δ = 0.

    ``step_mm`` is the central-difference step for the slope dV/dδ (the level set's area) and
    the largest Newton step; a flat V (no level set crossing) returns the last δ.
    """
    lo, hi = values.min(axis=1), values.max(axis=1)
    near = (lo < 8 * step_mm) & (hi > -8 * step_mm)  # where the level can move within ±8 steps
    inside = volumes_mm3[~near & (hi <= -8 * step_mm)].sum()
    vals, vols = values[near], volumes_mm3[near]
    delta = 0.0
    for _ in range(MAX_ITER):
        v = inside + volume_below(vals, vols, delta)
        if abs(v - target_mm3) <= VOLUME_RTOL * target_mm3:
            break
        slope = (volume_below(vals, vols, delta + 0.5 * step_mm)
                 - volume_below(vals, vols, delta - 0.5 * step_mm)) / step_mm
        if slope <= 0:
            break
        delta += float(np.clip((target_mm3 - v) / slope, -step_mm, step_mm))
    return delta
