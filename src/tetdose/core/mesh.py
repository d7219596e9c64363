"""TetMesh: a linear tetrahedral mesh in patient coordinates (mm), the structure every step shares.

Conventions: ``points_mm`` (N, 3) float64 in the patient frame (DICOM LPS, mm); ``tets`` (M, 4)
intp vertex ids, positively oriented (signed volume > 0); ``neighbors[k, i]`` is the tetrahedron
across the face of ``k`` opposite its vertex ``i`` (−1 on the boundary).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np

from tetdose._typing import FloatArray, IntArray
from tetdose.errors import MeshError, TopologyMismatchError

#: A tetrahedron whose |6·volume| is below this fraction of (longest edge)³ is degenerate.
DEGENERATE_REL = 1e-10
#: point_data key holding, for a region-split mesh, the id of the geometric vertex a point copies.
PARENT_POINT = "parent_point"
#: Two vertices closer than this [mm] in every coordinate are coincident (a duplicate).
COINCIDENT_TOL_MM = 1e-6
#: Face i of a tetrahedron is made of the other three vertices, ordered so its normal points out.
FACE_VERTICES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]], dtype=np.intp)


def signed_volumes_mm3(points_mm: FloatArray, tets: IntArray) -> FloatArray:
    """Signed tetrahedron volumes [mm³]: det[b − a, c − a, d − a] / 6 (positive = right-handed)."""
    a = points_mm[tets[:, 0]]
    e1 = points_mm[tets[:, 1]] - a
    e2 = points_mm[tets[:, 2]] - a
    e3 = points_mm[tets[:, 3]] - a
    return np.einsum("ij,ij->i", e1, np.cross(e2, e3)) / 6.0


def compact_points(points_mm: FloatArray, tets: IntArray) -> tuple[FloatArray, IntArray, IntArray]:
    """Drop the points no tetrahedron uses and renumber the cells, keeping the points' order.

    Returns (kept points (P, 3), renumbered tets (M, 4) intp, ids of the kept points (P,)), so
    per-point arrays follow with ``values[kept_ids]``.
    """
    used, new_ids = np.unique(np.asarray(tets), return_inverse=True)
    return (np.ascontiguousarray(np.asarray(points_mm)[used]),
            np.ascontiguousarray(new_ids.reshape(np.shape(tets)), dtype=np.intp), used)


@dataclass(frozen=True, eq=False)
class TetMesh:
    """A tetrahedral mesh: points [mm], cells, optional region labels and extra arrays.

    Parameters
    ----------
    points_mm : (N, 3) float
        Vertex coordinates in the patient frame [mm].
    tets : (M, 4) int
        Vertex ids of each tetrahedron.
    region : (M,) int, optional
        Region label per tetrahedron (cell_data ``region``), kept through every step.
    point_data, cell_data : dict
        Further arrays of the input mesh, kept and written back out.
    """

    points_mm: FloatArray
    tets: IntArray
    region: IntArray | None = None
    point_data: dict[str, np.ndarray] = field(default_factory=dict)
    cell_data: dict[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        points = np.ascontiguousarray(self.points_mm, dtype=np.float64)
        tets = np.ascontiguousarray(self.tets, dtype=np.intp)
        if points.ndim != 2 or points.shape[1] != 3:
            raise MeshError(f"points_mm must have shape (N, 3), got {points.shape}")
        if tets.ndim != 2 or tets.shape[1] != 4:
            raise MeshError(f"tets must have shape (M, 4), got {tets.shape}")
        if len(tets) == 0:
            raise MeshError("the mesh has no tetrahedra; give a volume mesh (tetra cells)")
        bad = ~np.isfinite(points).all(axis=1)
        if bad.any():
            raise MeshError(
                f"{bad.sum()} point(s) have NaN or infinite coordinates (first ids: "
                f"{np.flatnonzero(bad)[:10].tolist()}); fix the mesh file"
            )
        if tets.min() < 0 or tets.max() >= len(points):
            raise MeshError(f"tetrahedron vertex ids must lie in [0, {len(points)}); fix the cells")
        object.__setattr__(self, "points_mm", points)
        object.__setattr__(self, "tets", tets)
        if self.region is not None:
            region = np.ascontiguousarray(self.region, dtype=np.int64).reshape(-1)
            if len(region) != len(tets):
                raise MeshError(f"region has {len(region)} values for {len(tets)} tetrahedra")
            object.__setattr__(self, "region", region)
        for name, arr in self.point_data.items():
            if len(arr) != len(points):
                raise MeshError(f"point_data {name!r} has {len(arr)} rows for {len(points)} points")
        for name, arr in self.cell_data.items():
            if len(arr) != len(tets):
                raise MeshError(f"cell_data {name!r} has {len(arr)} rows for {len(tets)} tetrahedra")

    @property
    def n_points(self) -> int:
        return len(self.points_mm)

    @property
    def n_tets(self) -> int:
        return len(self.tets)

    @cached_property
    def signed_volumes_mm3(self) -> FloatArray:
        """Signed volume of each tetrahedron [mm³]."""
        return signed_volumes_mm3(self.points_mm, self.tets)

    @property
    def volumes_mm3(self) -> FloatArray:
        """Volume of each tetrahedron [mm³] (checked positive by :meth:`check_cells`)."""
        return np.abs(self.signed_volumes_mm3)

    @cached_property
    def centroids_mm(self) -> FloatArray:
        """Centroid of each tetrahedron [mm]."""
        return self.points_mm[self.tets].mean(axis=1)

    @cached_property
    def neighbors(self) -> IntArray:
        """(M, 4) id of the tetrahedron across the face opposite vertex i, −1 on the boundary."""
        ids = self.tets
        if PARENT_POINT in self.point_data:  # faces match across region-split copies
            ids = np.asarray(self.point_data[PARENT_POINT], dtype=np.intp)[self.tets]
        faces = np.sort(ids[:, FACE_VERTICES].reshape(-1, 3), axis=1)
        order = np.lexsort(faces.T[::-1])
        sorted_faces = faces[order]
        same = np.all(sorted_faces[1:] == sorted_faces[:-1], axis=1)
        out = np.full(4 * self.n_tets, -1, dtype=np.intp)
        first, second = order[:-1][same], order[1:][same]
        if np.any(same[1:] & same[:-1]):
            raise MeshError("a face is shared by more than two tetrahedra; the mesh is not manifold")
        out[first] = second // 4
        out[second] = first // 4
        if PARENT_POINT not in self.point_data:
            self._refuse_duplicates_on(faces.reshape(-1, 4, 3)[out.reshape(-1, 4) < 0])
        return out.reshape(-1, 4)

    def _refuse_duplicates_on(self, boundary_faces: IntArray) -> None:
        """MeshError if distinct vertices of boundary faces coincide: regions that touch without
        sharing vertices (a non-conforming interface, where a transport walk would get lost)."""
        dup = self.coincident_vertices(np.unique(boundary_faces))
        if dup.size:
            raise MeshError(
                f"{dup.size} vertices coincide with another vertex on region interfaces (first "
                f"ids {dup[:10].tolist()}): the regions do not share vertices, so the mesh is not "
                "conforming; merge them with mesh.merged_duplicates(), or mesh the labels as one "
                "conforming mesh (tetdose mesh)"
            )

    def coincident_vertices(self, candidates: IntArray | None = None) -> IntArray:
        """Ids (among ``candidates``, default all) of vertices within ``COINCIDENT_TOL_MM`` of a
        distinct vertex with a lower id: the duplicates :meth:`merged_duplicates` removes."""
        ids = np.arange(self.n_points) if candidates is None else np.asarray(candidates)
        if ids.size < 2:
            return np.zeros(0, dtype=np.intp)
        key = np.round(self.points_mm[ids] / COINCIDENT_TOL_MM).astype(np.int64)
        order = np.lexsort(key.T[::-1])
        same = np.all(key[order][1:] == key[order][:-1], axis=1)
        return np.sort(ids[order[1:][same]])

    def merged_duplicates(self) -> TetMesh:
        """A copy with coincident vertices (within ``COINCIDENT_TOL_MM``) merged into one,
        so regions that touched through duplicated vertices share them (point_data of the
        first copy kept; ``PARENT_POINT`` dropped)."""
        key = np.round(self.points_mm / COINCIDENT_TOL_MM).astype(np.int64)
        _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
        keep = np.sort(first)
        new_id = np.empty(self.n_points, dtype=np.intp)
        rank = np.empty(len(first), dtype=np.intp)
        rank[np.argsort(first)] = np.arange(len(first))
        new_id[:] = rank[inverse.reshape(-1)]
        point_data = {k: np.asarray(v)[keep] for k, v in self.point_data.items()
                      if k != PARENT_POINT}
        return TetMesh(self.points_mm[keep], new_id[self.tets], self.region, point_data,
                       dict(self.cell_data))

    @cached_property
    def boundary_faces(self) -> IntArray:
        """(F, 3) vertex ids of the boundary triangles, oriented outwards."""
        k, i = np.nonzero(self.neighbors < 0)
        return self.tets[k[:, None], FACE_VERTICES[i]]

    def split_by_region(self) -> TetMesh:
        """A copy whose vertices are duplicated per region, so density may jump across regions.

        Each (vertex, region) pair becomes one point; ``point_data[PARENT_POINT]`` keeps the
        original vertex id (face adjacency still crosses region interfaces).
        """
        if self.region is None:
            return self
        keys = np.stack([self.tets.ravel(), np.repeat(self.region, 4)], axis=1)
        uniq, new_ids = np.unique(keys, axis=0, return_inverse=True)
        parent = uniq[:, 0]
        point_data = {k: np.asarray(v)[parent] for k, v in self.point_data.items()}
        if PARENT_POINT not in self.point_data:
            point_data[PARENT_POINT] = parent
        return TetMesh(self.points_mm[parent], new_ids.reshape(-1, 4), self.region, point_data,
                       dict(self.cell_data))

    def bounds_mm(self) -> tuple[FloatArray, FloatArray]:
        """Axis-aligned bounding box (min corner, max corner) [mm]."""
        return self.points_mm.min(axis=0), self.points_mm.max(axis=0)

    def bad_cells(self) -> tuple[IntArray, IntArray]:
        """Ids of inverted (negative volume) and of degenerate (near-zero volume) tetrahedra."""
        p = self.points_mm[self.tets]
        edges = np.concatenate([p[:, [1, 2, 3, 2, 3, 3]] - p[:, [0, 0, 0, 1, 1, 2]]], axis=1)
        longest = np.sqrt((edges**2).sum(axis=2).max(axis=1))
        six_v = 6.0 * self.signed_volumes_mm3
        degenerate = np.abs(six_v) <= DEGENERATE_REL * longest**3
        inverted = (six_v < 0) & ~degenerate
        return np.flatnonzero(inverted), np.flatnonzero(degenerate)

    def check_cells(self, *, context: str = "") -> None:
        """Raise :class:`MeshError` naming inverted or degenerate tetrahedra, if any."""
        inverted, degenerate = self.bad_cells()
        where = f" {context}" if context else ""
        if len(degenerate):
            raise MeshError(
                f"{len(degenerate)} degenerate (zero-volume) tetrahedra{where}, ids "
                f"{degenerate[:20].tolist()}; remesh or remove them"
            )
        if len(inverted):
            raise MeshError(
                f"{len(inverted)} inverted tetrahedra (negative volume){where}, ids "
                f"{inverted[:20].tolist()}; if the whole mesh uses the opposite vertex order, "
                "map it with `tetdose map --fix-orientation` (API: read_mesh(path, "
                "fix_orientation=True)), which writes a corrected mesh for the other commands"
            )

    def with_fixed_orientation(self) -> TetMesh:
        """A copy whose negatively oriented tetrahedra have two vertices swapped."""
        tets = self.tets.copy()
        neg = self.signed_volumes_mm3 < 0
        tets[neg, 1], tets[neg, 2] = self.tets[neg, 2], self.tets[neg, 1]
        return TetMesh(tets=tets, points_mm=self.points_mm, region=self.region,
                       point_data=self.point_data, cell_data=self.cell_data)

    def moved(self, points_mm: FloatArray) -> TetMesh:
        """The same tetrahedra on new vertex positions [mm] (a breathing phase)."""
        points_mm = np.asarray(points_mm, dtype=np.float64)
        if points_mm.shape != self.points_mm.shape:
            raise TopologyMismatchError(
                f"moved points have shape {points_mm.shape}, the mesh has {self.points_mm.shape}"
            )
        return TetMesh(points_mm, self.tets, self.region, dict(self.point_data),
                       dict(self.cell_data))

    def with_data(self, *, point_data: dict[str, Any] | None = None,
                  cell_data: dict[str, Any] | None = None) -> TetMesh:
        """A copy with point/cell arrays added or replaced."""
        pd = {**self.point_data, **(point_data or {})}
        cd = {**self.cell_data, **(cell_data or {})}
        return TetMesh(self.points_mm, self.tets, self.region, pd, cd)

    def same_topology(self, other: TetMesh) -> None:
        """Raise :class:`TopologyMismatchError` at the first cell where ``other`` differs."""
        if other.n_points != self.n_points or other.n_tets != self.n_tets:
            raise TopologyMismatchError(
                f"phase mesh has {other.n_points} points / {other.n_tets} tetrahedra, the "
                f"reference has {self.n_points} / {self.n_tets}; phases must share one topology"
            )
        diff = np.flatnonzero(np.any(other.tets != self.tets, axis=1))
        if len(diff):
            k = int(diff[0])
            raise TopologyMismatchError(
                f"tetrahedron {k} differs: {other.tets[k].tolist()} vs reference "
                f"{self.tets[k].tolist()} ({len(diff)} cells differ); phases must share one topology"
            )
