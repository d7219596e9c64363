"""Exact tetrahedron ∩ voxel volumes and first moments (the paper's eq. 6–7, computed exactly).

All coordinates are in *index space* u = q / spacing (q the grid frame, see ``tetdose.image``),
where voxel (i, j, k) is the unit box [i−½, i+½] × [j−½, j+½] × [k−½, k+½]. The rigid + diagonal
map from patient mm to u scales every volume by the same factor, so volume fractions and
barycentric moments are unchanged by it.

Method: a tetrahedron is cut by the voxel planes axis by axis (x slabs, then y, then z). Cutting a
tetrahedron by a plane and keeping one side gives a polyhedron that splits into at most three
tetrahedra (1 vertex kept: a corner tetrahedron; 2 kept: a wedge; 3 kept: a frustum — each a
prism with planar quads, cut along its diagonals). A slab piece is the tetrahedron clipped by the
slab's two planes: ≤ 9 tetrahedra after the x slab, ≤ 81 after the y slab; z pieces are not stored
but reduced to per-voxel volumes and first moments as differences of the moments below
consecutive z planes (one clip per plane). Volumes are sums of exact sub-tetrahedron volumes, so
the rows of F sum to 1 up to round-off.

Two entry kernels share the per-tet output layout (one slice per tetrahedron of length given by
its bounding-box voxel count, ``out_count`` says how much of it is filled):
``overlap_exact`` (this clipping) and ``overlap_monte_carlo`` (the paper's hit-and-miss estimate,
uniform points in the tetrahedron after Rocchini & Cignoni, "Generating random points in a
tetrahedron", J. Graphics Tools 5(4), 2000).
"""

import math

import numpy as np
from numba import njit, prange

from tetdose._random import next_uniform, seed_for

#: Pieces whose volume is below this fraction of the tetrahedron's are dropped (touching contacts).
_DROP_REL = 1e-13
_MAX_X = 9
_MAX_Y = 81


@njit(cache=True)
def _tet_volume(t):
    """|det[b − a, c − a, d − a]| / 6 of a (4, 3) array."""
    ax, ay, az = t[1, 0] - t[0, 0], t[1, 1] - t[0, 1], t[1, 2] - t[0, 2]
    bx, by, bz = t[2, 0] - t[0, 0], t[2, 1] - t[0, 1], t[2, 2] - t[0, 2]
    cx, cy, cz = t[3, 0] - t[0, 0], t[3, 1] - t[0, 1], t[3, 2] - t[0, 2]
    det = ax * (by * cz - bz * cy) - ay * (bx * cz - bz * cx) + az * (bx * cy - by * cx)
    return abs(det) / 6.0


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


@njit(cache=True)
def _index_range(lo, hi, n):
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
    v = _tet_volume(t)
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
        pz0, pz1 = _index_range(zlo, zhi, nz)
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
def _exact_one(tet, nx, ny, nz, voxel_out, vol_out, cen_out, start, xs, ys, tmp, zacc, cut,
               cum, prev):
    """Pairs of one tetrahedron (index-space (4, 3) array); returns the number written."""
    vol_tet = _tet_volume(tet)
    drop = _DROP_REL * vol_tet
    x0, x1 = _index_range(tet[:, 0].min(), tet[:, 0].max(), nx)
    written = 0
    for ix in range(x0, x1 + 1):
        n_x = _slab(tet.reshape(1, 4, 3), 1, 0, ix - 0.5, ix + 0.5, xs, tmp, cut)
        if n_x == 0:
            continue
        y0, y1 = _index_range(xs[:n_x, :, 1].min(), xs[:n_x, :, 1].max(), ny)
        for iy in range(y0, y1 + 1):
            n_y = _slab(xs, n_x, 1, iy - 0.5, iy + 0.5, ys, tmp, cut)
            if n_y == 0:
                continue
            z0, z1 = _index_range(ys[:n_y, :, 2].min(), ys[:n_y, :, 2].max(), nz)
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
def overlap_exact(points_u, tets, nx, ny, nz, offsets, voxel_out, vol_out, cen_out, out_count):
    """Exact pairs for every tetrahedron.

    points_u : (N, 3) vertex coordinates in index space; tets : (M, 4) vertex ids;
    offsets : (M + 1,) start of each tetrahedron's slice in the outputs (bounding-box counts);
    voxel_out : flat voxel ids; vol_out : overlap volume (index-space units, i.e. voxels);
    cen_out : (P, 3) centroid of each overlap (index space); out_count : (M,) pairs written.
    """
    n_tets = tets.shape[0]
    n_blocks = min(n_tets, 64)
    for b in prange(n_blocks):
        xs = np.empty((_MAX_X, 4, 3))
        ys = np.empty((_MAX_Y, 4, 3))
        tmp = np.empty((3 + 9, 4, 3))
        zacc = np.empty((nz + 1, 4))
        tet = np.empty((4, 3))
        cut = np.empty((4, 3))
        cum = np.empty(4)
        prev = np.empty(4)
        for k in range(b, n_tets, n_blocks):
            for v in range(4):
                for d in range(3):
                    tet[v, d] = points_u[tets[k, v], d]
            out_count[k] = _exact_one(tet, nx, ny, nz, voxel_out, vol_out, cen_out, offsets[k],
                                      xs, ys, tmp, zacc, cut, cum, prev)


@njit(cache=True, parallel=True)
def overlap_monte_carlo(points_u, tets, nx, ny, nz, n_samples, seed, offsets, voxel_out,
                        vol_out, cen_out, out_count):
    """Hit-and-miss estimate (paper eq. 7): F_kj = N_j / N_R with N_R uniform points per tet.

    Same layout as :func:`overlap_exact`; ``vol_out`` holds F_kj · Vol(T_k) and ``cen_out`` the
    mean position of the points that fell in voxel j. Points outside the grid are dropped.
    """
    n_tets = tets.shape[0]
    for k in prange(n_tets):
        state = seed_for(seed, 1, k)
        ids = np.empty(n_samples, dtype=np.int64)
        pts = np.empty((n_samples, 3))
        a = points_u[tets[k, 0]]
        e1 = points_u[tets[k, 1]] - a
        e2 = points_u[tets[k, 2]] - a
        e3 = points_u[tets[k, 3]] - a
        vol = abs(e1[0] * (e2[1] * e3[2] - e2[2] * e3[1]) - e1[1] * (e2[0] * e3[2] - e2[2] * e3[0])
                  + e1[2] * (e2[0] * e3[1] - e2[1] * e3[0])) / 6.0
        for r in range(n_samples):
            state, s = next_uniform(state)
            state, t = next_uniform(state)
            state, u = next_uniform(state)
            s, t, u = _fold_into_tet(s, t, u)
            for d in range(3):
                pts[r, d] = a[d] + s * e1[d] + t * e2[d] + u * e3[d]
            i = int(math.floor(pts[r, 0] + 0.5))
            j = int(math.floor(pts[r, 1] + 0.5))
            kk = int(math.floor(pts[r, 2] + 0.5))
            inside = 0 <= i < nx and 0 <= j < ny and 0 <= kk < nz
            ids[r] = ((kk * ny + j) * nx + i) if inside else -1
        order = np.argsort(ids, kind="mergesort")
        written = 0
        r = 0
        while r < n_samples:
            vid = ids[order[r]]
            count = 0
            c0 = 0.0
            c1 = 0.0
            c2 = 0.0
            while r < n_samples and ids[order[r]] == vid:
                c0 += pts[order[r], 0]
                c1 += pts[order[r], 1]
                c2 += pts[order[r], 2]
                count += 1
                r += 1
            if vid >= 0:
                w = offsets[k] + written
                voxel_out[w] = vid
                vol_out[w] = vol * count / n_samples
                cen_out[w, 0] = c0 / count
                cen_out[w, 1] = c1 / count
                cen_out[w, 2] = c2 / count
                written += 1
        out_count[k] = written


@njit(cache=True)
def _fold_into_tet(s, t, u):
    """Map a uniform point of the unit cube to a uniform point of the unit corner tetrahedron."""
    if s + t > 1.0:
        s, t = 1.0 - s, 1.0 - t
    if t + u > 1.0:
        t, u = 1.0 - u, 1.0 - s - t
    elif s + t + u > 1.0:
        s, u = 1.0 - t - u, s + t + u - 1.0
    return s, t, u
