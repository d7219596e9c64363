"""Triangle surfaces: reading, exact closest points, and rigid ICP registration.

* Closest point on a triangle: the Voronoi-region method of Ericson, *Real-Time Collision
  Detection* (2005) §5.1.5, vectorised over (point, triangle) pairs.
* Closest point on a surface: the nearest vertex distance d_v bounds the surface distance from
  above, so only triangles whose centroid lies within d_v + r_max (r_max = largest
  centroid-to-vertex distance) can hold the closest point; those are found with a k-d tree
  (``scipy.spatial.cKDTree``) and tested exactly. The result is exact, not approximate.
* Rigid registration: point-to-point ICP (Besl & McKay 1992) from a centroid-aligned start;
  each step pairs every source point with its closest surface point and solves the best rigid
  fit by the SVD method of Arun/Kabsch (with the reflection guard of Umeyama 1991).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tetdose._typing import FloatArray, IntArray
from tetdose.errors import MeshError

#: ICP stops when the RMS distance changes by less than this [mm] between iterations.
ICP_TOL_MM = 1e-10
ICP_MAX_ITER = 200


@dataclass(frozen=True, eq=False)
class Surface:
    """A triangle surface: ``vertices_mm`` (V, 3) and ``triangles`` (T, 3) vertex ids."""

    vertices_mm: FloatArray
    triangles: IntArray

    def __post_init__(self) -> None:
        v = np.ascontiguousarray(self.vertices_mm, dtype=np.float64)
        t = np.ascontiguousarray(self.triangles, dtype=np.intp)
        if v.ndim != 2 or v.shape[1] != 3 or t.ndim != 2 or t.shape[1] != 3 or len(t) == 0:
            raise MeshError(f"a surface needs (V, 3) vertices and (T, 3) triangles, got "
                            f"{v.shape} and {t.shape}")
        if t.min() < 0 or t.max() >= len(v):
            raise MeshError(f"surface triangle vertex ids must lie in [0, {len(v)})")
        object.__setattr__(self, "vertices_mm", v)
        object.__setattr__(self, "triangles", t)

    def area_centroid_mm(self) -> FloatArray:
        """Area-weighted centroid of the surface [mm]."""
        p = self.vertices_mm[self.triangles]
        area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
        return (area[:, None] * p.mean(axis=1)).sum(axis=0) / area.sum()

    def transformed(self, rotation: FloatArray, translation_mm: FloatArray) -> Surface:
        """The surface moved by x ↦ R x + t."""
        return Surface(self.vertices_mm @ np.asarray(rotation).T + translation_mm, self.triangles)


def read_surface(path: str | os.PathLike[str]) -> Surface:
    """Read a triangle surface (STL, OBJ, PLY, VTK/VTU …) with meshio."""
    import meshio

    path = Path(path)
    if not path.exists():
        raise MeshError(f"surface file {path} does not exist")
    try:
        m = meshio.read(path)
    except Exception as exc:  # meshio raises many types for unreadable files
        raise MeshError(f"cannot read surface {path}: {exc}; give an STL/OBJ/PLY file") from exc
    tris = [c.data for c in m.cells if c.type == "triangle"]
    if not tris:
        raise MeshError(f"{path} holds no triangles (cells: {sorted({c.type for c in m.cells})})"
                        "; give a triangulated surface")
    return Surface(np.asarray(m.points, dtype=np.float64)[:, :3], np.concatenate(tris))


def closest_point_on_triangles(p: FloatArray, a: FloatArray, b: FloatArray,
                               c: FloatArray) -> FloatArray:
    """Closest point of triangle (a, b, c) to p, row by row (all (P, 3)); Ericson §5.1.5."""
    def dot(x: FloatArray, y: FloatArray) -> FloatArray:
        return np.einsum("ij,ij->i", x, y)

    ab, ac, ap, bp, cp = b - a, c - a, p - a, p - b, p - c
    d1, d2, d3, d4, d5, d6 = dot(ab, ap), dot(ac, ap), dot(ab, bp), dot(ac, bp), dot(ab, cp), \
        dot(ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        out = a + ab * (vb / denom)[:, None] + ac * (vc / denom)[:, None]
        # Override in reverse priority so that the first matching region of Ericson's order wins.
        regions = [
            ((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0),
             lambda: b + ((d4 - d3) / ((d4 - d3) + (d5 - d6)))[:, None] * (c - b)),
            ((vb <= 0) & (d2 >= 0) & (d6 <= 0), lambda: a + (d2 / (d2 - d6))[:, None] * ac),
            ((d6 >= 0) & (d5 <= d6), lambda: c),
            ((vc <= 0) & (d1 >= 0) & (d3 <= 0), lambda: a + (d1 / (d1 - d3))[:, None] * ab),
            ((d3 >= 0) & (d4 <= d3), lambda: b),
            ((d1 <= 0) & (d2 <= 0), lambda: a),
        ]
        for mask, value in regions:
            if mask.any():
                out[mask] = value()[mask]
    return out


def closest_points(query_mm: FloatArray, surface: Surface) -> tuple[FloatArray, FloatArray]:
    """Exact closest surface points (P, 3) [mm] and distances (P,) [mm] of query points."""
    from scipy.spatial import cKDTree

    q = np.asarray(query_mm, dtype=np.float64).reshape(-1, 3)
    tri = surface.vertices_mm[surface.triangles]
    centroids = tri.mean(axis=1)
    r_max = np.sqrt(((tri - centroids[:, None]) ** 2).sum(axis=2)).max()
    d_vertex, _ = cKDTree(surface.vertices_mm).query(q)
    cand = cKDTree(centroids).query_ball_point(q, d_vertex * (1 + 1e-12) + r_max + 1e-12)
    counts = np.array([len(c) for c in cand])
    qid = np.repeat(np.arange(len(q)), counts)
    tid = np.concatenate([np.asarray(c, dtype=np.intp) for c in cand])
    cp = closest_point_on_triangles(q[qid], tri[tid, 0], tri[tid, 1], tri[tid, 2])
    d2 = ((cp - q[qid]) ** 2).sum(axis=1)
    order = np.lexsort((d2, qid))
    first = order[np.r_[0, np.flatnonzero(np.diff(qid[order])) + 1]]
    return cp[first], np.sqrt(d2[first])


def best_rigid(src: FloatArray, dst: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Least-squares rotation R and translation t with R·src + t ≈ dst (Arun/Kabsch/Umeyama)."""
    cs, cd = src.mean(axis=0), dst.mean(axis=0)
    u, _, vt = np.linalg.svd((src - cs).T @ (dst - cd))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    r = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return r, cd - r @ cs


@dataclass(frozen=True)
class RigidTransform:
    """x ↦ rotation @ x + translation_mm, with the final ICP RMS distance [mm]."""

    rotation: FloatArray
    translation_mm: FloatArray
    rms_mm: float
    iterations: int

    def apply(self, points_mm: FloatArray) -> FloatArray:
        return np.asarray(points_mm) @ self.rotation.T + self.translation_mm


def icp(source: Surface, target: Surface, *, max_iter: int = ICP_MAX_ITER,
        tol_mm: float = ICP_TOL_MM) -> RigidTransform:
    """Rigid ICP of ``source``'s vertices onto the ``target`` surface (centroid-aligned start)."""
    rot = np.eye(3)
    trans = target.area_centroid_mm() - source.area_centroid_mm()
    pts = source.vertices_mm
    rms_old, it = np.inf, 0
    for it in range(1, max_iter + 1):  # noqa: B007 - the count is reported
        cur = pts @ rot.T + trans
        cp, dist = closest_points(cur, target)
        rms = float(np.sqrt(np.mean(dist**2)))
        if abs(rms_old - rms) < tol_mm:
            break
        r, t = best_rigid(cur, cp)
        rot, trans = r @ rot, r @ trans + t
        rms_old = rms
    return RigidTransform(rot, trans, rms, it)
