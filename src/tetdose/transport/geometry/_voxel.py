"""njit voxel traversal in the grid frame (Amanatides & Woo, "A fast voxel traversal algorithm for
ray tracing", Eurographics 1987).

Grid frame: q = Dᵀ(p − origin) [mm]; voxel (i, j, k) spans ``lo + (i, j, k)·cell`` to
``lo + (i+1, j+1, k+1)·cell`` with ``lo = −spacing/2``. Along a ray q + t·d the next boundary
crossing on axis a is at ``t_max[a]`` and successive crossings are ``t_delta[a] = cell_a/|d_a|``
apart; the walk steps the axis with the smallest ``t_max`` (ties: lowest axis, then the other
axis follows with a zero-length step). The ray–box interval (entry into the grid from
vacuum) uses the slab method (Kay & Kajiya 1986).
"""

from typing import NamedTuple

import numpy as np
from numba import njit

from tetdose._jit import kernel
from tetdose._typing import FloatArray, IntArray


class VoxelGeometry(NamedTuple):
    """Flat arrays describing a voxel phantom in its grid frame (mm, g/cm³)."""

    lo: FloatArray  # (3,) grid-frame corner of voxel (0, 0, 0) [mm]
    cell: FloatArray  # (3,) voxel size [mm]
    n: IntArray  # (3,) voxels per axis (nx, ny, nz)
    density: FloatArray  # (nx·ny·nz,) density per flat voxel id [g/cm³]
    material: IntArray  # (nx·ny·nz,) material index m per flat voxel id; −m − 1 where the voxel
    #                     lists mesh triangles (hybrid worlds, :mod:`._geometry_world`)


@kernel
def box_interval(lo, cell, n, x, y, z, u, v, w):
    """Slab method: (t_enter, t_exit) of the ray in the box lo … lo + n·cell (empty: t0 > t1)."""
    t0 = -np.inf
    t1 = np.inf
    p = (x, y, z)
    d = (u, v, w)
    for a in range(3):
        hi = lo[a] + n[a] * cell[a]
        if d[a] != 0.0:
            ta = (lo[a] - p[a]) / d[a]
            tb = (hi - p[a]) / d[a]
            t0 = max(t0, min(ta, tb))
            t1 = min(t1, max(ta, tb))
        elif p[a] < lo[a] or p[a] > hi:
            return np.inf, -np.inf
    return t0, t1


@kernel
def voxel_index(g, x, y, z):
    """Voxel (i, j, k) holding a grid-frame point, clamped into the grid."""
    i = min(max(int(np.floor((x - g.lo[0]) / g.cell[0])), 0), g.n[0] - 1)
    j = min(max(int(np.floor((y - g.lo[1]) / g.cell[1])), 0), g.n[1] - 1)
    k = min(max(int(np.floor((z - g.lo[2]) / g.cell[2])), 0), g.n[2] - 1)
    return i, j, k


@kernel
def dda_axis(lo, cell, idx, p, d):
    """(step, t_max, t_delta) of one axis for a ray starting at coordinate p in voxel idx."""
    if d > 0.0:
        return 1, max((lo + (idx + 1) * cell - p) / d, 0.0), cell / d
    if d < 0.0:
        return -1, max((lo + idx * cell - p) / d, 0.0), -cell / d
    return 0, np.inf, np.inf


@kernel
def dda_init(g, i, j, k, x, y, z, u, v, w):
    """Amanatides–Woo set-up: (sx, sy, sz, tx, ty, tz, dx, dy, dz) from a point in voxel ijk."""
    sx, tx, dx = dda_axis(g.lo[0], g.cell[0], i, x, u)
    sy, ty, dy = dda_axis(g.lo[1], g.cell[1], j, y, v)
    sz, tz, dz = dda_axis(g.lo[2], g.cell[2], k, z, w)
    return sx, sy, sz, tx, ty, tz, dx, dy, dz


@njit(cache=True, inline="always")
def dda_step(i, j, k, ti, tj, tk, si, sj, sk, di, dj, dk, n):
    """One Amanatides–Woo step: the axis with the nearest boundary (ties: lowest axis) moves.

    Returns (i, j, k, ti, tj, tk, inside): the new cell, its boundary distances, and whether the
    cell lies in the ``n`` = (nx, ny, nz) grid.
    """
    t_next = min(ti, tj, tk)
    if ti == t_next:
        i += si
        ti += di
    elif tj == t_next:
        j += sj
        tj += dj
    else:
        k += sk
        tk += dk
    inside = 0 <= i < n[0] and 0 <= j < n[1] and 0 <= k < n[2]
    return i, j, k, ti, tj, tk, inside
