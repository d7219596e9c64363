"""njit geometry on a tetrahedral mesh: exit face along a ray, neighbour walk, entry, relocation.

Exit face (plane-based, after Ren et al., "Accelerating mesh-based Monte Carlo method on modern
CPU architectures", Biomed. Opt. Express 3:3223, 2012, §2.2): face f of tet k has outward unit
normal n_f and offset c_f (n_f·x = c_f on the face). For a ray p + t·d inside the tet the exit
distance is ``t* = min { (c_f − n_f·p) / (n_f·d) : n_f·d > 0, f ≠ entry face }``, clamped at 0.

**Tie rule.** Equal distances (rays through an edge or a vertex) go to the lowest face index
(strict ``<``). The photon then hops through the tets around the edge or vertex with zero-length
steps; each hop leaves through a face the ray points out of, so the hops turn monotonically
towards the tet that holds the ray. A ray tangent to a face may be attributed to either side of
it: both share the face's densities, so only the tally cell of a zero-volume path can change.
If a walk stalls (no face ahead, or more than ``MAX_ZERO_STEPS`` zero-length hops), the photon is
**relocated** by point location of a point nudged along the ray; the caller counts relocations.

**Memory.** A crossing is a dependent load: the next tet's records are known only once this tet's
exit face is. On entering a tet the walker therefore prefetches the records of the neighbours it
may enter next (:func:`prefetch_neighbours`), so the next cache miss overlaps this tet's
arithmetic. Tets are stored in Morton order (:mod:`tetdose.transport.geometry.tets`).

Entry from outside: Möller–Trumbore ray–triangle tests against the boundary faces, accelerated
by a uniform grid over the mesh's bounding box traversed with Amanatides–Woo (see
:mod:`tetdose.transport.geometry._voxel`). The first boundary hit tells whether the source point
is outside (hit an entering face: start there) or inside (hit a leaving face: walk back along
the ray to the source point).

Point location (the photons' Woodcock flights in dose mode,
:mod:`tetdose.transport.history._delta`): a second uniform grid over the mesh's bounding box
lists per cell the tets that may meet it (:func:`list_tets_per_cell`, CSR, about one cell per
tet); :func:`locate_point` tests those candidates' face planes. Pure geometry, no walk.
"""

from typing import NamedTuple

import numpy as np
from numba import njit

from tetdose._jit import kernel
from tetdose._typing import FloatArray, IntArray
from tetdose.transport.geometry._prefetch import prefetch
from tetdose.transport.geometry._voxel import box_interval, dda_axis, dda_step

#: Zero-length hops allowed in a row before the photon is relocated.
MAX_ZERO_STEPS = 64
#: ``link`` of a boundary face whose plane supports the whole mesh (every point behind it): a
#: photon leaving through it moves away from the mesh for good (n·x grows along the ray), so
#: no re-entry ray cast is needed. Other boundary faces: −1.
SUPPORTING = -2
#: Relative tolerance on barycentric coordinates in point location and triangle hits.
BARY_TOL = 1e-9
#: A point this far outside a tet's face planes [mm] still lies in it, where it lies strictly
#: inside none (:func:`locate_point`): above the planes' float32 rounding (``TetGeometry``).
LOCATE_TOL_MM = 1e-4


class TetGeometry(NamedTuple):
    """Flat arrays describing a tetrahedral mesh for the kernels (all mm, g/cm³).

    One crossing reads ``planes[k]`` (64 B: one cache line, the array starts on one),
    ``link[k]`` (16 B) and, with physics, ``density[k]`` and ``material[k]``: 116 B per tet,
    so a 215 k-tet mesh's walk records (25 MB) stay in a 32 MB L3 cache. The planes are float32
    (arithmetic in float64): the normal is rounded first and the offset taken from the rounded
    normal, so a face's plane lies within the offset's rounding, 2⁻²⁴·|c| (3·10⁻⁵ mm at 500 mm
    from the origin), of its three vertices; two tets sharing a face store one plane, negated,
    so every point lies on one side of it. The mesh entry reads ``bnd_tri`` (96 B per boundary
    face: one cache miss per ray–triangle test, not six through tets and points).
    """

    planes: FloatArray  # (M, 4, 4) float32 face f: outward unit normal (0:3), offset n·x (3) [mm]
    link: IntArray  # (M, 4) int32 4·(tet across face f) + (its local face index); −1 on the boundary
    density: FloatArray  # (M, 4) linear density ρ(x) = g·x + c: (gx, gy, gz [g/cm³/mm], c)
    material: IntArray  # (M,) int32 material index
    bnd_tet: IntArray  # (F,) owner tet of each boundary face
    bnd_tri: FloatArray  # (F, 4, 3) boundary face: vertex a, edges b − a, c − a, outward unit normal
    grid_lo: FloatArray  # (3,) acceleration grid lower corner [mm]
    grid_cell: FloatArray  # (3,) cell size [mm]
    grid_n: IntArray  # (3,) cells per axis
    cell_start: IntArray  # (C + 1,) CSR offsets into cell_items
    cell_items: IntArray  # boundary face ids per grid cell
    loc_lo: FloatArray  # (3,) point-location grid lower corner [mm] (the Woodcock box)
    loc_cell: FloatArray  # (3,) its cell size [mm]
    loc_n: IntArray  # (3,) its cells per axis
    loc_start: IntArray  # (L + 1,) CSR offsets into loc_items
    loc_items: IntArray  # tets that may meet each point-location cell (int32)
    rho_max: FloatArray  # (n_mat,) largest density [g/cm³] per material index in the box


# Layouts measured (bench_transport.py, 384 k-tet box, 1 core): inline="always" 3.8 → 4.9 M
# crossings/s on the old 7-array layout; planes (M,4,4) + packed link: 9.8 → 12 M/s (z rays),
# 7.7 M/s for isotropic rays. Slower: a branch-less select over all four faces (Yao et al. 2012
# style, 7.5 M/s), structure of arrays (7.1), float32 planes in one 128-byte record per tet (no
# gain once memory-bound, and 2e-5 mm plane error). Neighbour prefetch: ×1.9 on a 48 k-tet mesh
# (L3-resident), ×1.1–1.2 on 384 k tets (DRAM latency exceeds the per-tet arithmetic).
@njit(cache=True, inline="always")
def density_at(g, k, x, y, z):
    """Density [g/cm³] at (x, y, z) [mm] by the linear field of tet ``k``."""
    return g.density[k, 3] + g.density[k, 0] * x + g.density[k, 1] * y + g.density[k, 2] * z


@njit(cache=True, inline="always")
def exit_face(g, k, x, y, z, u, v, w, entry_face):
    """(face, distance [mm]) where the ray leaves tet ``k``; face −1 if no face lies ahead."""
    best_t = np.inf
    best_f = -1
    for f in range(4):
        if f == entry_face:
            continue
        den = g.planes[k, f, 0] * u + g.planes[k, f, 1] * v + g.planes[k, f, 2] * w
        if den > 0.0:
            t = (g.planes[k, f, 3] - (g.planes[k, f, 0] * x + g.planes[k, f, 1] * y
                                      + g.planes[k, f, 2] * z)) / den
            if t < best_t:
                best_t = t
                best_f = f
    if best_t < 0.0:
        best_t = 0.0
    return best_f, best_t


@njit(cache=True, inline="always")
def next_tet(g, k, f):
    """(tet, entry face) across face ``f`` of tet ``k``; tet −1 when it leaves the mesh."""
    nxt = g.link[k, f]
    return nxt >> 2, nxt & 3


@njit(cache=True, inline="always")
def prefetch_neighbours(g, k, entry, physics, tally):
    """Prefetch what a crossing into each neighbour of tet ``k`` (but ``entry``) will read.

    Planes and link always; density and material too with ``physics``; ``tally[neighbour]``
    when ``tally`` is not empty (the track-length estimator writes it on every crossing).
    """
    for f in range(4):
        nxt = g.link[k, f]
        if f != entry and nxt >= 0:
            kk = nxt >> 2
            prefetch(g.planes, kk)
            prefetch(g.link, kk)
            if physics:
                prefetch(g.density, kk)
                prefetch(g.material, kk)
            if tally.shape[0] > 0:
                prefetch(tally, kk)


@kernel
def contains(g, k, x, y, z, tol_mm):
    """True if (x, y, z) lies inside tet ``k`` up to ``tol_mm`` outside any face plane."""
    for f in range(4):
        s = (g.planes[k, f, 0] * x + g.planes[k, f, 1] * y + g.planes[k, f, 2] * z
             - g.planes[k, f, 3])
        if s > tol_mm:
            return False
    return True


@njit(cache=True, inline="always")
def locate_point(g, x, y, z):
    """Tet holding (x, y, z) [mm] by the point-location grid, or −1 outside the mesh.

    The grid cell's candidate tets (:func:`list_tets_per_cell`) are tested with the face planes
    (:func:`contains`): the first that contains the point is returned, or, for a point in none
    (the slivers the rounded planes leave along edges), the first within :data:`LOCATE_TOL_MM`.
    A random point misses the cache: the candidates' planes are prefetched all at once, so their
    loads overlap (490–630 → 410–470 ns per random location on the 162 k-tet box, measured).
    """
    fx = (x - g.loc_lo[0]) / g.loc_cell[0]
    fy = (y - g.loc_lo[1]) / g.loc_cell[1]
    fz = (z - g.loc_lo[2]) / g.loc_cell[2]
    if not (0.0 <= fx < g.loc_n[0] and 0.0 <= fy < g.loc_n[1] and 0.0 <= fz < g.loc_n[2]):
        return -1
    c = (int(fz) * g.loc_n[1] + int(fy)) * g.loc_n[0] + int(fx)
    for s in range(g.loc_start[c], g.loc_start[c + 1]):
        prefetch(g.planes, g.loc_items[s])
    for tol in (0.0, LOCATE_TOL_MM):
        for s in range(g.loc_start[c], g.loc_start[c + 1]):
            k = g.loc_items[s]
            if contains(g, k, x, y, z, tol):
                return k
    return -1


@kernel
def locate(g, x, y, z, tol_mm):
    """Brute-force point location: the first tet containing (x, y, z), else the first within
    ``tol_mm`` (at least :data:`LOCATE_TOL_MM`) outside its planes, or −1 (rare fallback)."""
    for tol in (0.0, max(tol_mm, LOCATE_TOL_MM)):
        for k in range(g.planes.shape[0]):
            if contains(g, k, x, y, z, tol):
                return k
    return -1


@kernel
def relocate(g, x, y, z, u, v, w, nudge_mm):
    """Tet holding the point nudged by ``nudge_mm`` along the ray (−1: it left the mesh)."""
    return locate(g, x + nudge_mm * u, y + nudge_mm * v, z + nudge_mm * w, nudge_mm)


@kernel
def ray_triangle(g, b, x, y, z, u, v, w):
    """Möller–Trumbore distance to boundary face ``b`` (inf if missed) and n·d of the face."""
    tri = g.bnd_tri[b]
    ax, ay, az = tri[0, 0], tri[0, 1], tri[0, 2]
    e1x, e1y, e1z = tri[1, 0], tri[1, 1], tri[1, 2]
    e2x, e2y, e2z = tri[2, 0], tri[2, 1], tri[2, 2]
    px, py, pz = v * e2z - w * e2y, w * e2x - u * e2z, u * e2y - v * e2x
    det = e1x * px + e1y * py + e1z * pz
    cos_n = tri[3, 0] * u + tri[3, 1] * v + tri[3, 2] * w
    if det == 0.0:
        return np.inf, cos_n
    inv = 1.0 / det
    sx, sy, sz = x - ax, y - ay, z - az
    b1 = (sx * px + sy * py + sz * pz) * inv
    qx, qy, qz = sy * e1z - sz * e1y, sz * e1x - sx * e1z, sx * e1y - sy * e1x
    b2 = (u * qx + v * qy + w * qz) * inv
    if b1 < -BARY_TOL or b2 < -BARY_TOL or b1 + b2 > 1.0 + BARY_TOL:
        return np.inf, cos_n
    return (e2x * qx + e2y * qy + e2z * qz) * inv, cos_n


@kernel
def first_boundary_hit(g, x, y, z, u, v, w, entering_only, t_min):
    """(boundary face id, distance [mm], n·d) of the first boundary face along the ray.

    Faces hit at distances ≤ ``t_min`` are skipped (``t_min`` slightly negative: hits a rounding
    error behind the start count). With ``entering_only`` only faces the ray enters through
    (n·d < 0) count: the re-entry of a photon that left the mesh. Walks the acceleration grid
    cell by cell (Amanatides–Woo) and stops as soon as the best hit lies within the cells
    already visited. Returns face −1 if the ray misses the mesh.
    """
    t0, t1 = box_interval(g.grid_lo, g.grid_cell, g.grid_n, x, y, z, u, v, w)
    best_b, best_t, best_cos = -1, np.inf, 0.0
    if t0 > t1:
        return best_b, best_t, best_cos
    t = max(t0, 0.0)
    lo, cell, n = g.grid_lo, g.grid_cell, g.grid_n
    i = min(max(int(np.floor((x + t * u - lo[0]) / cell[0])), 0), n[0] - 1)
    j = min(max(int(np.floor((y + t * v - lo[1]) / cell[1])), 0), n[1] - 1)
    k = min(max(int(np.floor((z + t * w - lo[2]) / cell[2])), 0), n[2] - 1)
    si, ti, di = dda_axis(lo[0], cell[0], i, x, u)
    sj, tj, dj = dda_axis(lo[1], cell[1], j, y, v)
    sk, tk, dk = dda_axis(lo[2], cell[2], k, z, w)
    while True:
        c = (k * n[1] + j) * n[0] + i
        for s in range(g.cell_start[c], g.cell_start[c + 1]):
            b = g.cell_items[s]
            tb, cb = ray_triangle(g, b, x, y, z, u, v, w)
            if tb > t_min and tb < best_t and (cb < 0.0 or not entering_only):
                best_b, best_t, best_cos = b, max(tb, 0.0), cb
        t_next = min(ti, tj, tk)
        if best_t <= t_next or t_next > t1:
            return best_b, best_t, best_cos
        i, j, k, ti, tj, tk, inside = dda_step(i, j, k, ti, tj, tk, si, sj, sk, di, dj, dk, n)
        if not inside:
            return best_b, best_t, best_cos


@kernel
def walk_to(g, k, x, y, z, u, v, w, length_mm):
    """Tet holding p + length·d, walking from tet ``k`` at p (pure geometry; −1 if it leaves).

    Also returns the number of relocations the walk needed.
    """
    entry = -1
    remaining = length_mm
    zero_steps = 0
    relocations = 0
    while True:
        f, t = exit_face(g, k, x, y, z, u, v, w, entry)
        if f >= 0 and t >= remaining:
            return k, relocations
        if f < 0 or zero_steps > MAX_ZERO_STEPS:
            relocations += 1
            return locate(g, x + remaining * u, y + remaining * v, z + remaining * w,
                          1e-9 * (1.0 + remaining)), relocations
        zero_steps = zero_steps + 1 if t == 0.0 else 0
        x, y, z = x + t * u, y + t * v, z + t * w
        remaining -= t
        k, entry = next_tet(g, k, f)
        if k < 0:
            return -1, relocations


@kernel
def enter_mesh(g, x, y, z, u, v, w):
    """Start of a source ray: (tet, x, y, z, relocations); tet −1 if the ray misses the mesh.

    Outside the mesh is vacuum: a ray from an outside point moves to its first boundary hit.
    """
    b, t, cos_n = first_boundary_hit(g, x, y, z, u, v, w, False, -BARY_TOL * g.grid_cell[0])
    if b < 0:
        return -1, x, y, z, 0
    k = g.bnd_tet[b]
    hx, hy, hz = x + t * u, y + t * v, z + t * w
    if cos_n <= 0.0:
        return k, hx, hy, hz, 0
    # the first boundary face is a leaving one: the source point is inside; walk back to it
    kk, nreloc = walk_to(g, k, hx, hy, hz, -u, -v, -w, t)
    return kk, x, y, z, nreloc


@njit(cache=True)
def list_tets_per_cell(planes, tet_lo, tet_hi, lo, cell, n, pad):
    """Point-location grid (built once per mesh): per cell of the uniform grid ``lo``, ``cell``,
    ``n``, the tets that may hold a point of it. Returns (start (L + 1,), items (int32)).

    Tet k is listed in cell C when its bounding box ``tet_lo[k] … tet_hi[k]`` overlaps C's (both
    grown by ``pad`` [mm]) and C's box is not wholly outside one of k's face planes:
    n_f·c − c_f ≤ Σ_axis |n_f,axis|·h_axis + pad, with c, h C's centre and half sizes (a
    separating-axis test on the face normals; conservative: a listed tet may miss the cell, a
    tet that meets it is always listed).
    """
    m = planes.shape[0]
    n_cells = n[0] * n[1] * n[2]
    count = np.zeros(n_cells + 1, dtype=np.intp)
    items = np.empty(0, dtype=np.int32)
    fill = np.empty(0, dtype=np.intp)
    ib = np.empty((m, 2, 3), dtype=np.intp)
    for k in range(m):
        for a in range(3):
            i0 = int(np.floor((tet_lo[k, a] - pad - lo[a]) / cell[a]))
            i1 = int(np.floor((tet_hi[k, a] + pad - lo[a]) / cell[a]))
            ib[k, 0, a] = min(max(i0, 0), n[a] - 1)
            ib[k, 1, a] = min(max(i1, 0), n[a] - 1)
    for rep in range(2):  # count, then fill
        if rep == 1:
            for c in range(1, count.shape[0]):
                count[c] += count[c - 1]
            items = np.empty(count[-1], dtype=np.int32)
            fill = count[:-1].copy()
        for k in range(m):
            for kz in range(ib[k, 0, 2], ib[k, 1, 2] + 1):
                cz = lo[2] + (kz + 0.5) * cell[2]
                for jy in range(ib[k, 0, 1], ib[k, 1, 1] + 1):
                    cy = lo[1] + (jy + 0.5) * cell[1]
                    for ix in range(ib[k, 0, 0], ib[k, 1, 0] + 1):
                        cx = lo[0] + (ix + 0.5) * cell[0]
                        outside = False
                        for f in range(4):
                            nx_, ny_, nz_ = planes[k, f, 0], planes[k, f, 1], planes[k, f, 2]
                            reach = 0.5 * (abs(nx_) * cell[0] + abs(ny_) * cell[1]
                                           + abs(nz_) * cell[2]) + pad
                            if nx_ * cx + ny_ * cy + nz_ * cz - planes[k, f, 3] > reach:
                                outside = True
                                break
                        if outside:
                            continue
                        c = (kz * n[1] + jy) * n[0] + ix
                        if rep == 0:
                            count[c + 1] += 1
                        else:
                            items[fill[c]] = k
                            fill[c] += 1
    return count, items
