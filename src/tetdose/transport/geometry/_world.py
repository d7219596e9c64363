"""njit geometry of the transport world: a tetrahedral mesh inside a voxel grid (either may be empty).

One world, one frame: with a grid, everything (mesh points, sources) is in the grid frame
q = Dᵀ(p − origin) [mm] of :mod:`tetdose.transport.geometry._voxel`; without one, the patient
frame. Cells are numbered globally: tets ``0 … M−1`` (Morton order), voxels ``M + vid``.

Inside the mesh the mesh is the only truth; outside it, the voxels. A voxel cut by the mesh
surface is traversed as a voxel only up to the surface: each voxel of the mesh's bounding box
lists the boundary triangles whose bounding box (grown by :data:`LIST_PAD_MM`) touches it (CSR,
built by :mod:`tetdose.transport.geometry.world`), and the voxel flight tests those triangles
(Möller–Trumbore) on the stretch of the ray inside the voxel; such voxels carry their material
index m as −m − 1, so the flight knows without a second load per step. The first *entering* hit
(n·d < 0) hands the photon to the owner tet at the exact hit point. A photon leaving the mesh
continues in the voxel holding its exit point or, outside the grid, flies through vacuum to
whichever comes first: the mesh's next entering face (:func:`~._geometry_tet.first_boundary_hit`)
or the grid (a mesh may reach beyond the CT, e.g. a breathing phase; without a grid the mesh is
alone in vacuum).
"""

from typing import NamedTuple

import numpy as np
from numba import njit

from tetdose._jit import kernel
from tetdose._typing import IntArray
from tetdose.transport.geometry._tet import (
    BARY_TOL,
    TetGeometry,
    enter_mesh,
    first_boundary_hit,
    ray_triangle,
    walk_to,
)
from tetdose.transport.geometry._voxel import VoxelGeometry, box_interval, voxel_index

#: Growth of each boundary triangle's box when listing it per voxel [mm]: a triangle ending on a
#: voxel plane is listed on both sides, so a hit that rounds onto the plane is never missed.
LIST_PAD_MM = 1e-6
#: Hits this far behind the current point still count [mm] (rounding at a switch).
HIT_TOL_MM = 1e-9


class WorldGeometry(NamedTuple):
    """Mesh part, voxel part and the per-voxel boundary-triangle lists (flat arrays)."""

    tet: TetGeometry  # 0 tets: a voxel-only world
    vox: VoxelGeometry  # 0 voxels: a mesh-only world (vacuum around the mesh)
    tri_lo: IntArray  # (3,) voxel index (i, j, k) of the first voxel of the listed box
    tri_n: IntArray  # (3,) voxels per axis of the listed box (0: no lists)
    tri_start: IntArray  # (C + 1,) CSR offsets per listed voxel into tri_items
    tri_items: IntArray  # boundary face ids (rows of tet.bnd_tri)


@kernel
def voxel_id(g, i, j, k):
    """Flat voxel id of (i, j, k): (k·ny + j)·nx + i."""
    return (k * g.n[1] + j) * g.n[0] + i


@njit(cache=True, inline="always")
def voxel_ijk(g, vid):
    """(i, j, k) of a flat voxel id."""
    nx, ny = g.n[0], g.n[1]
    return vid % nx, (vid // nx) % ny, vid // (nx * ny)


@kernel
def mesh_hit_in_voxel(wg, i, j, k, x, y, z, u, v, w, t_lo, t_hi):
    """(boundary face, distance [mm]) of the nearest entering hit with t_lo < t ≤ t_hi among
    the triangles listed for voxel (i, j, k); face −1 if none. Distances from (x, y, z)."""
    li, lj, lk = i - wg.tri_lo[0], j - wg.tri_lo[1], k - wg.tri_lo[2]
    n = wg.tri_n
    if li < 0 or lj < 0 or lk < 0 or li >= n[0] or lj >= n[1] or lk >= n[2]:
        return -1, np.inf
    c = (lk * n[1] + lj) * n[0] + li
    best_b, best_t = -1, t_hi
    for s in range(wg.tri_start[c], wg.tri_start[c + 1]):
        b = wg.tri_items[s]
        tb, cos_n = ray_triangle(wg.tet, b, x, y, z, u, v, w)
        if cos_n < 0.0 and tb > t_lo and tb <= best_t:
            if tb < best_t or best_b < 0:
                best_b, best_t = b, tb
    return best_b, best_t


@kernel
def cell_material(wg, cell):
    """Material index of a global cell (tet or ``M + voxel id``; a voxel listing triangles holds
    −m − 1)."""
    m = wg.tet.planes.shape[0]
    if cell < m:
        return wg.tet.material[cell]
    mv = wg.vox.material[cell - m]
    return mv if mv >= 0 else -mv - 1


@kernel
def voxel_cell_at(wg, x, y, z):
    """Global cell of the voxel holding (x, y, z), or −1 if the point lies outside the grid."""
    g = wg.vox
    tol = HIT_TOL_MM
    for a, p in enumerate((x, y, z)):
        if p < g.lo[a] - tol or p > g.lo[a] + g.n[a] * g.cell[a] + tol:
            return -1
    i, j, k = voxel_index(g, x, y, z)
    return wg.tet.planes.shape[0] + voxel_id(g, i, j, k)


@kernel
def vacuum_flight(wg, x, y, z, u, v, w, t_min):
    """From a point outside the grid and the mesh, the first cell along the ray: (cell, x, y, z);
    cell −1 if the ray meets neither. Mesh faces nearer than ``t_min`` [mm] are ignored."""
    best = np.inf
    cell = -1
    if wg.tet.planes.shape[0] > 0:
        b, t, _ = first_boundary_hit(wg.tet, x, y, z, u, v, w, True, t_min)
        if b >= 0:
            best, cell = t, wg.tet.bnd_tet[b]
    if wg.vox.density.shape[0] > 0:
        g = wg.vox
        t0, t1 = box_interval(g.lo, g.cell, g.n, x, y, z, u, v, w)
        if t0 <= t1 and t1 > HIT_TOL_MM and t0 >= -HIT_TOL_MM and t0 < best:
            t0 = max(t0, 0.0)
            best = t0
            cell = voxel_cell_at(wg, x + t0 * u, y + t0 * v, z + t0 * w)
    if cell < 0:
        return -1, x, y, z
    return cell, x + best * u, y + best * v, z + best * w


@kernel
def start_cell(wg, x, y, z, u, v, w):
    """Where a source ray starts: (global cell, x, y, z, relocations); cell −1 if it misses.

    If the first mesh boundary face ahead is a leaving one the point is inside the mesh (walk
    back to it); else, inside the grid it starts in its voxel (the voxel flight finds the mesh
    ahead), outside it flies through vacuum to the grid or the mesh (:func:`vacuum_flight`).
    """
    m = wg.tet.planes.shape[0]
    if wg.vox.density.shape[0] == 0:  # the mesh alone: one ray cast decides
        k, x, y, z, n_reloc = enter_mesh(wg.tet, x, y, z, u, v, w)
        return k, x, y, z, n_reloc
    if m > 0:
        t0, t1 = box_interval(wg.tet.grid_lo, wg.tet.grid_cell, wg.tet.grid_n, x, y, z, u, v, w)
        if t0 <= t1 and t1 >= 0.0:
            b, t, cos_n = first_boundary_hit(wg.tet, x, y, z, u, v, w, False,
                                             -BARY_TOL * wg.tet.grid_cell[0])
            if b >= 0 and cos_n > 0.0:
                k, n_reloc = walk_to(wg.tet, wg.tet.bnd_tet[b], x + t * u, y + t * v,
                                     z + t * w, -u, -v, -w, t)
                if k >= 0:
                    return k, x, y, z, n_reloc
    cell = voxel_cell_at(wg, x, y, z)
    if cell >= 0:
        return cell, x, y, z, 0
    cell, x, y, z = vacuum_flight(wg, x, y, z, u, v, w, -BARY_TOL)
    return cell, x, y, z, 0


@njit(cache=True)
def list_triangles_per_voxel(bnd_tri, lo, cell, n, pad):
    """Per-voxel boundary-triangle lists over the triangles' voxel box (built once per world).

    Triangle b (corner a, edges e1, e2 as in ``bnd_tri``) is listed in voxel V when their boxes
    overlap (grown by ``pad`` [mm]) and V's box meets the triangle's plane: |n·(c − a)| ≤
    Σ_axis |n_axis|·h_axis + pad, with c, h the voxel's centre and half sizes (conservative: a
    listed triangle may miss the voxel, a missed one never touches it).
    Returns (tri_lo (3,), tri_n (3,), start (C + 1,), items).
    """
    f = bnd_tri.shape[0]
    ib = np.zeros((f, 2, 3), dtype=np.intp)
    box_lo = np.full(3, np.iinfo(np.intp).max, dtype=np.intp)
    box_hi = np.full(3, -1, dtype=np.intp)
    for b in range(f):
        for a in range(3):
            p0 = bnd_tri[b, 0, a]
            p1 = p0 + bnd_tri[b, 1, a]
            p2 = p0 + bnd_tri[b, 2, a]
            i0 = int(np.floor((min(p0, p1, p2) - pad - lo[a]) / cell[a]))
            i1 = int(np.floor((max(p0, p1, p2) + pad - lo[a]) / cell[a]))
            ib[b, 0, a] = min(max(i0, 0), n[a] - 1)
            ib[b, 1, a] = min(max(i1, 0), n[a] - 1)
            box_lo[a] = min(box_lo[a], ib[b, 0, a])
            box_hi[a] = max(box_hi[a], ib[b, 1, a])
    if f == 0:
        return (np.zeros(3, dtype=np.intp), np.zeros(3, dtype=np.intp),
                np.zeros(1, dtype=np.intp), np.zeros(0, dtype=np.intp))
    tn = box_hi - box_lo + 1
    count = np.zeros(tn[0] * tn[1] * tn[2] + 1, dtype=np.intp)
    items = np.empty(0, dtype=np.intp)
    fill = np.empty(0, dtype=np.intp)
    for rep in range(2):  # count, then fill

        if rep == 1:
            for c in range(1, count.shape[0]):
                count[c] += count[c - 1]
            items = np.empty(count[-1], dtype=np.intp)
            fill = count[:-1].copy()
        for b in range(f):
            nx_, ny_, nz_ = bnd_tri[b, 3, 0], bnd_tri[b, 3, 1], bnd_tri[b, 3, 2]
            ax, ay, az = bnd_tri[b, 0, 0], bnd_tri[b, 0, 1], bnd_tri[b, 0, 2]
            reach = (abs(nx_) * cell[0] + abs(ny_) * cell[1] + abs(nz_) * cell[2]) * 0.5 + pad
            for k in range(ib[b, 0, 2], ib[b, 1, 2] + 1):
                cz = lo[2] + (k + 0.5) * cell[2] - az
                for j in range(ib[b, 0, 1], ib[b, 1, 1] + 1):
                    cy = lo[1] + (j + 0.5) * cell[1] - ay
                    for i in range(ib[b, 0, 0], ib[b, 1, 0] + 1):
                        cx = lo[0] + (i + 0.5) * cell[0] - ax
                        if abs(nx_ * cx + ny_ * cy + nz_ * cz) > reach:
                            continue
                        c = ((k - box_lo[2]) * tn[1] + (j - box_lo[1])) * tn[0] + i - box_lo[0]
                        if rep == 0:
                            count[c + 1] += 1
                        else:
                            items[fill[c]] = b
                            fill[c] += 1
    return box_lo, tn, count, items
