"""Mesh → kernel arrays for the tetrahedral walker (:class:`~._geometry_tet.TetGeometry`).

Per tet: the four face planes (outward unit normal n_f, offset c_f = n_f·a for a vertex a of the
face; float32, one cache line per tet: :class:`~._tet.TetGeometry`, :func:`float32_planes`), the
packed neighbour link ``4·k' + f'`` (k' the tet across face f, f' the same face's index in k';
−1 on the boundary, :data:`SUPPORTING` on a boundary face no photon can come back through), the
linear density ρ(x) = ∇ρ·x + c solved from the four vertex densities, and the material.
Boundary faces (corner, two edges, outward normal) go into a uniform grid (CSR) for the entry
ray cast.

Tet order: :func:`morton_order` sorts tets along a Z-order (Morton) curve of their centroids
(21 bits per axis), so tets near in space are near in memory. Meshers emit tets in an order
unrelated to space. Pure walk on a 384 k-tet box, larger than the cache (bench_transport.py,
1 core, with neighbour prefetch): numbered at random 6.9–7.0 M crossings/s, after Morton sorting
8.0–8.6; the box's own slice-by-slice order (z fastest) gives 9.4 for isotropic rays and 12.7 for
rays along z, the order's best case.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from tetdose._typing import FloatArray, IntArray
from tetdose.core.mesh import FACE_VERTICES, TetMesh
from tetdose.errors import MeshError
from tetdose.transport.geometry._tet import SUPPORTING, TetGeometry, list_tets_per_cell

_MORTON_BITS = 21
#: Point-location grid: cells per tet (sets the cell size), cap per axis, and the growth of the
#: tets' boxes and face planes when listing them per cell [mm] (≥ the location tolerance).
LOC_CELLS_PER_TET = 1.0
LOC_MAX_CELLS_PER_AXIS = 512
LOC_PAD_MM = 2e-4
#: Bytes of a cache line: the planes array starts on one, so a tet's planes fill one line.
CACHE_LINE = 64


def aligned_copy(a: np.ndarray, align: int = CACHE_LINE) -> np.ndarray:
    """A C-contiguous copy of ``a`` whose data start on an ``align``-byte boundary."""
    buf = np.empty(a.nbytes + align, dtype=np.uint8)
    start = -buf.ctypes.data % align
    out = buf[start:start + a.nbytes].view(a.dtype).reshape(a.shape)
    out[...] = a
    return out


def float32_planes(normals: FloatArray, on_face: FloatArray, link: IntArray) -> np.ndarray:
    """(M, 4, 4) float32 planes from unit ``normals`` (M, 4, 3) and a point ``on_face`` (M, 4, 3)
    of each face [mm]: the normal is rounded first and the offset c = n·a taken from the rounded
    normal in float64, then rounded (so the plane misses the face's vertices by c's rounding,
    2⁻²⁴·|c|, not by the normal's times |a|); a face shared by two tets (``link`` ≥ 0, packed
    4·k' + f') gets one plane, stored negated in the tet of higher index, so both tets put every
    point on the same side of it."""
    n32 = normals.astype(np.float32)
    planes = np.empty(normals.shape[:2] + (4,), dtype=np.float32)
    planes[..., :3] = n32
    planes[..., 3] = np.einsum("mfi,mfi->mf", n32.astype(np.float64), on_face)
    k, f = np.nonzero(link >= 0)
    k2, f2 = link[k, f] >> 2, link[k, f] & 3
    lower = k < k2
    planes[k2[lower], f2[lower]] = -planes[k[lower], f[lower]]
    return planes


def morton_order(points_mm: FloatArray) -> IntArray:
    """Permutation sorting points along the Z-order curve of their quantized coordinates.

    Coordinates are scaled to integers 0 … 2²¹−1 over the bounding box; the key interleaves
    their bits (x in bit 0 of each triple, then y, z). Ties keep the input order (stable sort).
    """
    p = np.asarray(points_mm, dtype=np.float64)
    lo, span = p.min(axis=0), np.ptp(p, axis=0)
    scale = (2**_MORTON_BITS - 1) / np.where(span > 0, span, 1.0)
    q = ((p - lo) * scale).astype(np.uint64)
    key = np.zeros(len(p), dtype=np.uint64)
    for bit in range(_MORTON_BITS):
        for axis in range(3):
            key |= ((q[:, axis] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(3 * bit + axis)
    return np.argsort(key, kind="stable").astype(np.intp)


def _boundary_grid(points: FloatArray, tri: IntArray) -> tuple[FloatArray, ...]:
    """Uniform grid over the boundary triangles (CSR cell → face ids); ~sqrt(F/12) cells/axis."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    pad = 1e-6 * max(float(np.max(hi - lo)), 1.0)
    lo, hi = lo - pad, hi + pad
    n = np.full(3, int(np.clip(np.sqrt(len(tri) / 12.0), 1, 128)), dtype=np.intp)
    cell = (hi - lo) / n
    p = points[tri]
    i0 = np.clip(np.floor((p.min(axis=1) - lo) / cell).astype(np.intp), 0, n - 1)
    # a triangle ending exactly on a cell plane is not listed in the next cell (the traversal
    # only stops once the best hit lies within the cells visited, so it still finds it)
    i1 = np.clip(np.ceil((p.max(axis=1) - lo) / cell).astype(np.intp) - 1, i0, n - 1)
    span = (i1 - i0).max(axis=0) + 1
    cells, faces = [], []
    for d in np.ndindex(*span):
        idx = i0 + np.array(d)
        ok = np.all(idx <= i1, axis=1)
        cells.append((idx[ok, 2] * n[1] + idx[ok, 1]) * n[0] + idx[ok, 0])
        faces.append(np.flatnonzero(ok))
    c, f = np.concatenate(cells), np.concatenate(faces)
    order = np.argsort(c, kind="stable")
    start = np.searchsorted(c[order], np.arange(int(np.prod(n)) + 1)).astype(np.intp)
    return lo, cell, n, start, f[order].astype(np.intp)


def location_grid(points: FloatArray, tets: IntArray, planes: FloatArray
                  ) -> tuple[FloatArray, FloatArray, IntArray, IntArray, IntArray]:
    """Point-location grid of a mesh: (lo, cell, n, start, items) over the mesh's bounding box
    grown by 1e-6 of its extent (a point on the box lies outside the mesh), about
    :data:`LOC_CELLS_PER_TET` cells per tet, each listing the tets that may meet it
    (:func:`~._tet.list_tets_per_cell`). Memory: 8·(L + 1) + 4·Σ listed bytes."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    pad = 1e-6 * max(float(np.max(hi - lo)), 1.0)
    lo, hi = lo - pad, hi + pad
    ext = hi - lo
    h = (float(np.prod(ext)) / max(len(tets) * LOC_CELLS_PER_TET, 1.0)) ** (1.0 / 3.0)
    n = np.clip(np.ceil(ext / h), 1, LOC_MAX_CELLS_PER_AXIS).astype(np.intp)
    cell = ext / n
    p = points[tets]
    start, items = list_tets_per_cell(planes, p.min(axis=1), p.max(axis=1), lo, cell, n,
                                      LOC_PAD_MM)
    return lo, cell, n, start, items


def material_density_max(material: IntArray, density_g_cm3: FloatArray,
                         n_materials: int) -> FloatArray:
    """(n_materials,) largest of ``density_g_cm3`` [g/cm³] per material index (0 if none)."""
    out = np.zeros(n_materials)
    if len(material):
        np.maximum.at(out, np.asarray(material, dtype=np.intp), density_g_cm3)
    return out


def supporting_faces(points_mm: FloatArray, planes: FloatArray) -> np.ndarray:
    """Boolean per face plane (F, 4: outward unit normal, offset): every point lies behind it
    (up to 1e-9 of the mesh's extent). Tested against the convex hull's vertices only."""
    from scipy.spatial import ConvexHull, QhullError

    try:
        hull = points_mm[ConvexHull(points_mm).vertices]
    except QhullError:  # flat or degenerate point sets: test every point
        hull = points_mm
    tol = 1e-9 * max(float(np.ptp(points_mm, axis=0).max()), 1.0)
    out = np.empty(len(planes), dtype=bool)
    for lo in range(0, len(planes), 4096):
        pl = planes[lo:lo + 4096]
        out[lo:lo + 4096] = (hull @ pl[:, :3].T - pl[:, 3]).max(axis=0) <= tol
    return out


def mesh_geometry(mesh: TetMesh, density_g_cm3: FloatArray, material: IntArray,
                  order: IntArray | None = None,
                  to_frame: Callable[[FloatArray], FloatArray] | None = None) -> TetGeometry:
    """Kernel arrays of a mesh; kernel tet i is ``mesh`` tet ``order[i]`` (default: identity).

    ``to_frame`` maps the points into the world's frame (a rigid map: the grid frame of a
    hybrid world); planes, density gradients and the entry grid are built there.
    """
    mesh.check_cells(context="for transport")
    pts, tets, nb = mesh.points_mm, mesh.tets, mesh.neighbors
    if to_frame is not None:
        pts = to_frame(pts)
    rho = np.asarray(density_g_cm3, dtype=np.float64)
    if rho.shape != (mesh.n_points,) or not np.all(np.isfinite(rho)) or np.any(rho < 0):
        raise MeshError(f"vertex densities must be {mesh.n_points} finite values ≥ 0 g/cm³")
    order = np.arange(mesh.n_tets) if order is None else np.asarray(order, dtype=np.intp)
    inv = np.empty_like(order)
    inv[order] = np.arange(len(order))
    tets, nb = tets[order], nb[order]
    fv = tets[:, FACE_VERTICES]  # (M, 4, 3)
    a, b, c = pts[fv[..., 0]], pts[fv[..., 1]], pts[fv[..., 2]]
    planes = np.empty((len(tets), 4, 4))
    normals = np.cross(b - a, c - a)
    normals /= np.linalg.norm(normals, axis=2, keepdims=True)
    flip = np.einsum("mfi,mfi->mf", normals, pts[tets] - a) > 0
    normals[flip] *= -1.0
    planes[..., :3] = normals
    planes[..., 3] = np.einsum("mfi,mfi->mf", normals, a)
    edges = pts[tets[:, 1:]] - pts[tets[:, :1]]
    grad = np.linalg.solve(edges, (rho[tets[:, 1:]] - rho[tets[:, :1]])[..., None])[..., 0]
    density = np.column_stack([grad, rho[tets[:, 0]] - np.einsum("mi,mi->m", grad,
                                                                  pts[tets[:, 0]])])
    k, f = np.nonzero(nb >= 0)
    link = np.full_like(nb, -1)
    face_back = np.argmax(mesh.neighbors[nb[k, f]] == order[k][:, None], axis=1)
    link[k, f] = 4 * inv[nb[k, f]] + face_back
    bk, bf = np.nonzero(nb < 0)
    sup = supporting_faces(pts, planes[bk, bf])
    link[bk[sup], bf[sup]] = SUPPORTING
    tri = tets[bk[:, None], FACE_VERTICES[bf]]
    corner = pts[tri[:, 0]]
    bnd_tri = np.stack([corner, pts[tri[:, 1]] - corner, pts[tri[:, 2]] - corner,
                        planes[bk, bf, :3]], axis=1)
    c_ = np.ascontiguousarray
    material = c_(np.asarray(material)[order], dtype=np.int32)
    # linear density: its largest value in a tet is at a vertex
    rho_max = material_density_max(material, rho[tets].max(axis=1),
                                   int(material.max()) + 1 if len(material) else 0)
    return TetGeometry(aligned_copy(float32_planes(normals, a, link)), c_(link, dtype=np.int32),
                       c_(density), material,
                       c_(bk, dtype=np.intp), c_(bnd_tri), *_boundary_grid(pts, tri),
                       *location_grid(pts, tets, planes), rho_max)


def empty_mesh_geometry() -> TetGeometry:
    """The mesh part of a voxel-only world: no tets, no boundary faces, one empty grid cell."""
    z3 = np.zeros(3)
    return TetGeometry(np.zeros((0, 4, 4), np.float32), np.zeros((0, 4), np.int32),
                       np.zeros((0, 4)), np.zeros(0, np.int32),  # planes, link, density, material
                       np.zeros(0, np.intp), np.zeros((0, 4, 3)),  # boundary faces
                       z3, np.ones(3), np.ones(3, np.intp), np.zeros(2, np.intp),
                       np.zeros(0, np.intp),  # entry grid
                       z3.copy(), np.ones(3), np.ones(3, np.intp), np.zeros(2, np.intp),
                       np.zeros(0, np.int32),  # point-location grid
                       np.zeros(0))
