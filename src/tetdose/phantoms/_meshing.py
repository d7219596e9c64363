"""Mesh a label image into a conforming multi-region tetrahedral mesh without an external mesher.

Method: a structured grid of cubes of edge ``target_edge_mm`` (independent of the voxel size and
shifted by a fraction of an edge, so its planes do not coincide with voxel planes) covers the
labelled voxels; each cube is split into six Kuhn tetrahedra (conforming, see :mod:`tetdose.core.tetgrid`). A
tetrahedron is kept when the label of the voxel containing its centroid is one of ``label_ids``,
and that label becomes its region. Optionally, interface and boundary vertices are then
snapped onto the label surfaces, every cell kept positively oriented. The grid is built in the
image's grid frame q = Dᵀ(p − origin), so any orthonormal direction matrix (flipped axes
included) is honoured.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from tetdose.core import tetgrid
from tetdose.core.image import Image, ImageGrid
from tetdose.core.mesh import TetMesh, compact_points, signed_volumes_mm3
from tetdose.errors import ImageError, MeshError
from tetdose.phantoms import _shapes

#: Fraction of an edge by which the cube grid is shifted off the labelled region's voxel planes.
GRID_SHIFT_FRAC = 0.37
#: Blur [voxels] of the label indicators whose ½ level set the interface vertices snap to.
SNAP_SIGMA_VOX = 0.75
#: Largest snap step, as a fraction of the cube edge.
SNAP_MAX_STEP_FRAC = 0.35
#: No snap step may shrink a cell below this fraction of its grid volume.
MIN_VOLUME_FRAC = 0.05
#: Cells clamped flat against the image border below this fraction of h³/6 are dropped.
MIN_CELL_FRAC = 1e-2


def voxel_lookup(grid: ImageGrid, array: np.ndarray, points_mm: np.ndarray) -> np.ndarray:
    """Value of the voxel containing each point (nearest centre); −1 for points outside."""
    idx = np.floor(grid.physical_to_index(points_mm) + 0.5).astype(np.int64)
    size = np.array(grid.size)
    inside = np.all((idx >= 0) & (idx < size), axis=1)
    out = np.full(len(points_mm), -1, dtype=np.int64)
    i, j, k = idx[inside].T
    out[inside] = array[k, j, i]
    return out


def _blurred_indicator(mask: np.ndarray) -> np.ndarray:
    pad = int(np.ceil(4 * SNAP_SIGMA_VOX))
    padded = np.pad(mask.astype(np.float64), pad, mode="edge")
    return _shapes.gaussian_filter(padded, SNAP_SIGMA_VOX)[pad:-pad, pad:-pad, pad:-pad]


def _trilinear(phi: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Trilinear interpolation of phi (nz, ny, nx) at continuous (i, j, k), clamped to the grid."""
    hi = np.array(phi.shape[::-1]) - 1
    idx = np.clip(idx, 0, hi)
    base = np.minimum(np.floor(idx).astype(np.int64), np.maximum(hi - 1, 0))
    t = idx - base
    out = np.zeros(len(idx))
    for corner in range(8):
        o = np.array([(corner >> a) & 1 for a in range(3)])
        c = np.minimum(base + o, hi)
        w = np.prod(np.where(o == 1, t, 1.0 - t), axis=1)
        out += w * phi[c[:, 2], c[:, 1], c[:, 0]]
    return out


def snap_to_labels(nodes_q: np.ndarray, tets: np.ndarray, region: np.ndarray, arr: np.ndarray,
                   spacing_mm: np.ndarray, ids: np.ndarray, edge_mm: float, iterations: int
                   ) -> np.ndarray:
    """Move interface vertices onto the ½ level set of the blurred label indicator (grid frame).

    A vertex on the interface a | b (a > b) follows Newton steps δ = −(φ − ½) ∇φ / |∇φ|², φ the
    indicator of label a (of the meshed set on the outer boundary) blurred by
    ``SNAP_SIGMA_VOX``, each step at most ``SNAP_MAX_STEP_FRAC`` × edge; vertices on junctions
    stay, and no cell shrinks below ``MIN_VOLUME_FRAC`` of its volume (``tetgrid.guarded``).
    """
    code = tetgrid.surface_vertices(len(nodes_q), tets, region)
    n_codes = int(region.max()) + 2
    vol0 = signed_volumes_mm3(nodes_q, tets)
    for c in np.unique(code[code >= 0]):
        own, other = divmod(int(c), n_codes)
        phi = _blurred_indicator(arr == own if other >= 0 else np.isin(arr, ids))
        v = np.flatnonzero(code == c)
        for _ in range(iterations):
            idx = nodes_q[v] / spacing_mm
            value = _trilinear(phi, idx) - 0.5
            grad = np.stack([(_trilinear(phi, idx + 0.5 * e) - _trilinear(phi, idx - 0.5 * e))
                             / spacing_mm[a] for a, e in enumerate(np.eye(3))], axis=1)
            g2 = (grad**2).sum(axis=1)
            step = np.where(g2[:, None] > 1e-12, -value[:, None] * grad / np.maximum(g2, 1e-12
                                                                                      )[:, None], 0)
            norm = np.linalg.norm(step, axis=1, keepdims=True)
            step *= np.minimum(1.0, SNAP_MAX_STEP_FRAC * edge_mm / np.maximum(norm, 1e-300))
            new = nodes_q.copy()
            new[v] += step
            nodes_q = tetgrid.guarded(nodes_q, new, tets, vol0, MIN_VOLUME_FRAC)
    return nodes_q


def mesh_labels(labels: Image, label_ids: Iterable[int] | None = None, target_edge_mm: float = 8.0,
                *, snap_iterations: int = 0) -> TetMesh:
    """Conforming tetrahedral mesh of the voxels whose label is in ``label_ids`` (default: ≠ 0).

    Parameters
    ----------
    labels : Image
        Integer label image (0 = background).
    label_ids : iterable of int, optional
        Labels to mesh; each becomes a mesh region (cell_data ``region``).
    target_edge_mm : float
        Edge of the grid cubes [mm]; a cube of edge h gives 6 tetrahedra of volume h³/6.
    snap_iterations : int
        Newton steps snapping interface vertices onto the label surfaces (see
        :func:`snap_to_labels`); 0 keeps the staircase of whole cells, whose region volumes
        match the label volumes best for structures thinner than about two edges.
    """
    arr = np.asarray(labels.array)
    if not np.issubdtype(arr.dtype, np.integer):
        raise ImageError(f"labels must be an integer image, got dtype {arr.dtype}; round it first")
    ids = np.unique(arr[arr != 0]) if label_ids is None else np.unique(list(label_ids))
    selected = np.isin(arr, ids)
    if not selected.any():
        raise ImageError(f"no voxel carries a label in {ids.tolist()}; check the label ids")
    h = float(target_edge_mm)
    if not h > 0:
        raise MeshError(f"target_edge_mm must be positive, got {target_edge_mm}")
    grid = labels.grid
    spacing = grid.spacing_mm
    kji = np.nonzero(selected)
    lo = np.array([kji[2].min(), kji[1].min(), kji[0].min()]) * spacing - 0.5 * spacing
    hi = np.array([kji[2].max(), kji[1].max(), kji[0].max()]) * spacing + 0.5 * spacing
    start = lo - GRID_SHIFT_FRAC * h
    cells = tuple(int(n) for n in np.ceil((hi - start) / h))
    box = grid.bounds_grid_frame()
    nodes_q = np.clip(tetgrid.grid_nodes(start, np.full(3, h), cells), box[0], box[1])
    tets = tetgrid.grid_tets(cells, "kuhn")
    vol = signed_volumes_mm3(nodes_q, tets)
    centroids = grid.origin_mm + nodes_q[tets].mean(axis=1) @ grid.direction.T
    region = voxel_lookup(grid, arr, centroids)
    keep = np.isin(region, ids) & (vol > MIN_CELL_FRAC * h**3 / 6.0)
    nodes_q, tets, _ = compact_points(nodes_q, tets[keep])
    region = region[keep]
    nodes_q = snap_to_labels(nodes_q, tets, region, arr, spacing, ids, h, snap_iterations)
    points = grid.origin_mm + nodes_q @ grid.direction.T
    if np.linalg.det(grid.direction) < 0:  # a reflection flips every cell's orientation
        tets = tets[:, [0, 2, 1, 3]]
    mesh = TetMesh(points, tets, region)
    mesh.check_cells(context="in the structured label mesh")
    return mesh
