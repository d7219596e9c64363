"""Checks of a labelled tetrahedral mesh against its label image: quality, volume, surface,
conformity.

* Dihedral angle at edge (i, j) of a tetrahedron: the angle between the outward normals n_k, n_l
  of the two faces through that edge is π − θ_ij, so θ_ij = π − arccos(n_k · n_l).
* Volume per label vs its voxel volume (voxel count × voxel volume).
* Surface distance: |φ_l| at the vertices and centroids of the boundary faces of region l, with
  φ_l the unsmoothed signed distance of the label mask (zero on the voxel faces between label
  and non-label; :mod:`tetdose.meshing.distance`), mean and 95th percentile [mm].
* Conformity: every face is shared by at most two tetrahedra (``TetMesh.neighbors``), faces
  between regions are shared (there are no boundary faces inside the outer surface), and no two
  distinct vertices coincide (``TetMesh.coincident_vertices``).
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from tetdose._constants import MM3_PER_CM3
from tetdose._typing import FloatArray
from tetdose.core.image import Image
from tetdose.core.mesh import FACE_VERTICES, TetMesh
from tetdose.meshing.distance import signed_distance
from tetdose.meshing.labels import as_label_array

#: The six edges (i, j) of a tetrahedron and the two other vertices (k, l).
_EDGES = [(0, 1, 2, 3), (0, 2, 1, 3), (0, 3, 1, 2), (1, 2, 0, 3), (1, 3, 0, 2), (2, 3, 0, 1)]


def dihedral_angles_deg(points_mm: FloatArray, tets: np.ndarray) -> FloatArray:
    """(M, 6) interior dihedral angles [degrees] of each tetrahedron at its six edges."""
    p = points_mm[tets]
    out = np.empty((len(tets), 6))
    for e, (i, j, k, l) in enumerate(_EDGES):
        axis = p[:, j] - p[:, i]
        n1 = np.cross(axis, p[:, k] - p[:, i])
        n2 = np.cross(axis, p[:, l] - p[:, i])
        cos = np.einsum("ij,ij->i", n1, n2) / (np.linalg.norm(n1, axis=1)
                                              * np.linalg.norm(n2, axis=1) + 1e-300)
        out[:, e] = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    return out


def conformity(mesh: TetMesh) -> dict[str, int]:
    """Counts: boundary faces, interface faces (shared by two regions), coincident vertices,
    and boundary faces that lie on another boundary face's plane twice (gaps between regions:
    faces whose three vertex positions repeat)."""
    nb = mesh.neighbors  # raises MeshError if a face is shared by more than two tetrahedra
    k, i = np.nonzero(nb < 0)
    faces = mesh.tets[k[:, None], FACE_VERTICES[i]]
    key = np.sort(np.round(mesh.points_mm[faces], 6).reshape(len(faces), -1), axis=1)
    _, counts = np.unique(key, axis=0, return_counts=True)
    region = mesh.region if mesh.region is not None else np.zeros(mesh.n_tets, dtype=np.int64)
    kk, ii = np.nonzero(nb >= 0)
    interface = int(np.count_nonzero(region[kk] < region[nb[kk, ii]]))
    return {"boundary_faces": int(len(faces)), "interface_faces": interface,
            "coincident_vertices": int(mesh.coincident_vertices().size),
            "duplicated_boundary_faces": int(np.count_nonzero(counts > 1))}


def mesh_checks(mesh: TetMesh, labels: Image, label_ids: Iterable[int] | None = None) -> dict:
    """Per-label report: tets, volume [cm³] vs voxel volume, dihedral min/median [°], surface
    distance mean/95th [mm]; plus the whole mesh's conformity and quality."""
    arr = as_label_array(labels.array)
    region = mesh.region if mesh.region is not None else np.ones(mesh.n_tets, dtype=np.int64)
    ids = np.unique(region) if label_ids is None else np.asarray(sorted(label_ids))
    angles = dihedral_angles_deg(mesh.points_mm, mesh.tets)
    nb = mesh.neighbors
    out: dict = {"n_tets": mesh.n_tets, "n_points": mesh.n_points,
                 "min_dihedral_deg": float(angles.min()),
                 "median_dihedral_deg": float(np.median(angles)),
                 "inverted": int(len(mesh.bad_cells()[0])), "conformity": conformity(mesh),
                 "labels": {}}
    vox = labels.grid.voxel_volume_mm3
    for lab in ids.tolist():
        in_lab = region == lab
        mask = arr == lab
        voxel_mm3 = float(np.count_nonzero(mask)) * vox
        mesh_mm3 = float(mesh.volumes_mm3[in_lab].sum())
        entry = {"tets": int(in_lab.sum()), "volume_cm3": mesh_mm3 / MM3_PER_CM3,
                 "voxel_volume_cm3": voxel_mm3 / MM3_PER_CM3,
                 "volume_error_pct": 100.0 * (mesh_mm3 / voxel_mm3 - 1.0) if voxel_mm3 else None}
        if in_lab.any():
            a = angles[in_lab]
            entry.update(min_dihedral_deg=float(a.min()), median_dihedral_deg=float(np.median(a)))
        if in_lab.any() and mask.any():
            kk, ii = np.nonzero(in_lab[:, None] & ((nb < 0) | ~in_lab[np.maximum(nb, 0)]))
            tri = mesh.points_mm[mesh.tets[kk[:, None], FACE_VERTICES[ii]]]
            samples = np.concatenate([tri.reshape(-1, 3), tri.mean(axis=1)])
            dist = np.abs(signed_distance(mask, labels.grid)(samples))
            entry.update(surface_distance_mean_mm=float(dist.mean()),
                         surface_distance_p95_mm=float(np.percentile(dist, 95)))
        out["labels"][str(lab)] = entry
    return out
