"""Tetrahedron ∩ voxel overlap by splitting clipped pieces into tetrahedra (numba kernels).

The fallback of :mod:`tetdose.core._overlap_kernels` when a polyhedron would exceed its vertex
capacity, and the primitives both share. Cutting a tetrahedron by a plane and keeping one side
leaves ≤ 3 tetrahedra (1 vertex kept: a corner tetrahedron; 2: a wedge; 3: a frustum — prisms
with planar quads, cut along their diagonals): ≤ 9 after an x slab, ≤ 81 after a y slab; z slab
values are differences of the moments below consecutive z planes. Exact, but the pieces
proliferate, which is why the polyhedron method is the default.
"""

import math

import numpy as np
from numba import njit, prange

from tetdose._jit import kernel

#: Pieces whose volume is below this fraction of the tetrahedron's are dropped (touching contacts).
DROP_REL = 1e-13
_MAX_X = 9
_MAX_Y = 81


@kernel
def tet_volume(t):
    """|det[b − a, c − a, d − a]| / 6 of a (4, 3) array."""
    ax, ay, az = t[1, 0] - t[0, 0], t[1, 1] - t[0, 1], t[1, 2] - t[0, 2]
    bx, by, bz = t[2, 0] - t[0, 0], t[2, 1] - t[0, 1], t[2, 2] - t[0, 2]
    cx, cy, cz = t[3, 0] - t[0, 0], t[3, 1] - t[0, 1], t[3, 2] - t[0, 2]
    det = ax * (by * cz - bz * cy) - ay * (bx * cz - bz * cx) + az * (bx * cy - by * cx)
    return abs(det) / 6.0


# --------------------------------------------------------------------------- convex polyhedra
# A polyhedron is (pos (C, 3), nbr (C, 3), n): vertex positions, the three neighbours of each
# vertex, and the vertex count (−1 once a clip overflowed the capacity C; clips pass it on).

#: Neighbours of the vertices of a positively oriented tetrahedron, in the cyclic order that
#: makes every face walk run counter-clockwise seen from outside (positive fan volumes).
@njit(cache=True, inline="always")
def _put(out, n, p0, p1, p2, p3):
    for a in range(3):
        out[n, 0, a] = p0[a]
        out[n, 1, a] = p1[a]
        out[n, 2, a] = p2[a]
        out[n, 3, a] = p3[a]


@njit(cache=True)
def _clip(t, axis, c, sign, out, n, cut):
    """Append to ``out`` (from row ``n``) the tetrahedra of {x ∈ t : sign·(x[axis] − c) ≤ 0}.

    Returns the new row count. Vertices on the plane count as kept-side boundary points.
    ``cut`` is a (4, 3) scratch array for the edge–plane intersections (no allocation here: this
    is the innermost call; allocating three small arrays per call made it ~30× slower).
    """
    s0 = sign * (t[0, axis] - c)
    s1 = sign * (t[1, axis] - c)
    s2 = sign * (t[2, axis] - c)
    s3 = sign * (t[3, axis] - c)
    nn = (s0 < 0.0) + (s1 < 0.0) + (s2 < 0.0) + (s3 < 0.0)
    if nn == 0:
        return n
    if nn == 4:
        out[n] = t
        return n + 1
    # Kept (negative) vertices first, in a fixed order; then the others.
    neg0 = neg1 = neg2 = pos0 = pos1 = pos2 = 0
    i_neg = 0
    i_pos = 0
    for v in range(4):
        sv = s0 if v == 0 else s1 if v == 1 else s2 if v == 2 else s3
        if sv < 0.0:
            if i_neg == 0:
                neg0 = v
            elif i_neg == 1:
                neg1 = v
            else:
                neg2 = v
            i_neg += 1
        else:
            if i_pos == 0:
                pos0 = v
            elif i_pos == 1:
                pos1 = v
            else:
                pos2 = v
            i_pos += 1
    if nn == 1:
        _cut(t, neg0, pos0, s0, s1, s2, s3, cut, 0)
        _cut(t, neg0, pos1, s0, s1, s2, s3, cut, 1)
        _cut(t, neg0, pos2, s0, s1, s2, s3, cut, 2)
        _put(out, n, t[neg0], cut[0], cut[1], cut[2])
        return n + 1
    if nn == 2:  # wedge: triangles (a, ac, ad) and (b, bc, bd)
        _cut(t, neg0, pos0, s0, s1, s2, s3, cut, 0)
        _cut(t, neg0, pos1, s0, s1, s2, s3, cut, 1)
        _cut(t, neg1, pos0, s0, s1, s2, s3, cut, 2)
        _cut(t, neg1, pos1, s0, s1, s2, s3, cut, 3)
        b = t[neg1]
        _put(out, n, t[neg0], cut[0], cut[1], b)
        _put(out, n + 1, cut[0], cut[1], b, cut[2])
        _put(out, n + 2, cut[1], b, cut[2], cut[3])
        return n + 3
    # nn == 3, frustum: triangles (a, b, c) and (ad, bd, cd)
    _cut(t, neg0, pos0, s0, s1, s2, s3, cut, 0)
    _cut(t, neg1, pos0, s0, s1, s2, s3, cut, 1)
    _cut(t, neg2, pos0, s0, s1, s2, s3, cut, 2)
    a, b, cc = t[neg0], t[neg1], t[neg2]
    _put(out, n, a, b, cc, cut[0])
    _put(out, n + 1, b, cc, cut[0], cut[1])
    _put(out, n + 2, cc, cut[0], cut[1], cut[2])
    return n + 3


@njit(cache=True, inline="always")
def _cut(t, a, b, s0, s1, s2, s3, cut, row):
    """cut[row] = the point where edge (a, b) of t crosses the plane (s = signed distances)."""
    sa = s0 if a == 0 else s1 if a == 1 else s2 if a == 2 else s3
    sb = s0 if b == 0 else s1 if b == 1 else s2 if b == 2 else s3
    f = sa / (sa - sb)
    for d in range(3):
        cut[row, d] = t[a, d] + f * (t[b, d] - t[a, d])


@njit(cache=True)
def _slab(src, n_src, axis, lo, hi, out, tmp, cut):
    """Clip ``src[:n_src]`` to lo ≤ x[axis] ≤ hi into ``out``; return the count."""
    n = 0
    for p in range(n_src):
        m = _clip(src[p], axis, hi, 1.0, tmp, 0, cut)
        for q in range(m):
            n = _clip(tmp[q], axis, lo, -1.0, out, n, cut)
    return n


@kernel
def index_range(lo, hi, n):
    """Voxels [first, last] along an axis that a piece spanning [lo, hi] (index space) can touch."""
    first = max(0, int(math.floor(lo + 0.5)))
    last = min(n - 1, int(math.floor(hi + 0.5)))
    return first, last


@njit(cache=True)
def _below(t, c, tmp, cut, out4):
    """out4 = (volume, ∫x, ∫y, ∫z) of the part of tetrahedron t with z ≤ c."""
    m = _clip(t, 2, c, 1.0, tmp, 0, cut)
    out4[:] = 0.0
    for q in range(m):
        _add_moments(tmp[q], out4)


@njit(cache=True, inline="always")
def _add_moments(t, out4):
    v = tet_volume(t)
    out4[0] += v
    for d in range(3):
        out4[1 + d] += v * 0.25 * (t[0, d] + t[1, d] + t[2, d] + t[3, d])


@njit(cache=True)
def _column(ys, n_y, nz, z0, tmp, cut, zacc, cum, prev):
    """Add each piece's volume and moments per z slab to zacc (rows relative to slab z0).

    Slab values are differences of the cumulative moments below consecutive planes z = iz + ½
    (one clip per plane instead of two per slab); parts below/above the grid are left out.
    """
    for p in range(n_y):
        zlo = ys[p, :, 2].min()
        zhi = ys[p, :, 2].max()
        pz0, pz1 = index_range(zlo, zhi, nz)
        if pz0 > pz1:
            continue
        if zlo < pz0 - 0.5:
            _below(ys[p], pz0 - 0.5, tmp, cut, prev)
        else:
            prev[:] = 0.0
        for iz in range(pz0, pz1 + 1):
            if zhi > iz + 0.5:
                _below(ys[p], iz + 0.5, tmp, cut, cum)
            else:
                cum[:] = 0.0
                _add_moments(ys[p], cum)
            for e in range(4):
                zacc[iz - z0, e] += cum[e] - prev[e]
                prev[e] = cum[e]


@njit(cache=True)
def _tets_exact_one(tet, nx, ny, nz, voxel_out, vol_out, cen_out, start, xs, ys, tmp, zacc, cut,
               cum, prev):
    """Pairs of one tetrahedron (index-space (4, 3) array); returns the number written."""
    vol_tet = tet_volume(tet)
    drop = DROP_REL * vol_tet
    x0, x1 = index_range(tet[:, 0].min(), tet[:, 0].max(), nx)
    written = 0
    for ix in range(x0, x1 + 1):
        n_x = _slab(tet.reshape(1, 4, 3), 1, 0, ix - 0.5, ix + 0.5, xs, tmp, cut)
        if n_x == 0:
            continue
        y0, y1 = index_range(xs[:n_x, :, 1].min(), xs[:n_x, :, 1].max(), ny)
        for iy in range(y0, y1 + 1):
            n_y = _slab(xs, n_x, 1, iy - 0.5, iy + 0.5, ys, tmp, cut)
            if n_y == 0:
                continue
            z0, z1 = index_range(ys[:n_y, :, 2].min(), ys[:n_y, :, 2].max(), nz)
            zacc[: z1 - z0 + 1] = 0.0
            _column(ys, n_y, nz, z0, tmp, cut, zacc, cum, prev)
            for r in range(z1 - z0 + 1):
                if zacc[r, 0] > drop:
                    w = start + written
                    voxel_out[w] = ((z0 + r) * ny + iy) * nx + ix
                    vol_out[w] = zacc[r, 0]
                    for d in range(3):
                        cen_out[w, d] = zacc[r, 1 + d] / zacc[r, 0]
                    written += 1
    return written


@njit(cache=True, parallel=True)
def overlap_tetsplit(points_u, tets, nx, ny, nz, offsets, voxel_out, vol_out, cen_out, out_count,
                     which):
    """Pairs of the tetrahedra ``which`` by tetrahedra splitting, into the layout of
    :func:`tetdose.core._overlap_kernels.overlap_exact` (the polyhedra that overflowed)."""
    n_blocks = min(which.shape[0], 64)
    for b in prange(n_blocks):
        xs = np.empty((_MAX_X, 4, 3))
        ys = np.empty((_MAX_Y, 4, 3))
        tmp = np.empty((3 + 9, 4, 3))
        zacc = np.empty((nz + 1, 4))
        tet = np.empty((4, 3))
        cut = np.empty((4, 3))
        cum = np.empty(4)
        prev = np.empty(4)
        for i in range(b, which.shape[0], n_blocks):
            k = which[i]
            for v in range(4):
                for d in range(3):
                    tet[v, d] = points_u[tets[k, v], d]
            out_count[k] = _tets_exact_one(tet, nx, ny, nz, voxel_out, vol_out, cen_out,
                                           offsets[k], xs, ys, tmp, zacc, cut, cum, prev)
