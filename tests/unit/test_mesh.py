"""TetMesh: volumes, adjacency, validation errors, topology checks."""

import numpy as np
import pytest

from tetdose.core.mesh import FACE_VERTICES, TetMesh, compact_points, signed_volumes_mm3
from tetdose.errors import MeshError, TopologyMismatchError

from helpers import box_mesh


def test_box_volumes_sum_to_box_and_are_positive():
    m = box_mesh([0, 0, 0], [3, 4, 5], (3, 2, 2), jitter=0.2)
    assert m.volumes_mm3.sum() == pytest.approx(60.0, rel=1e-12)
    assert (m.signed_volumes_mm3 > 0).all()


def test_neighbors_are_symmetric_and_boundary_is_closed():
    m = box_mesh([0, 0, 0], [1, 1, 1], (2, 2, 2))
    nb = m.neighbors
    for k, i in zip(*np.nonzero(nb >= 0), strict=True):
        assert k in nb[nb[k, i]]
    # Boundary triangles: 6 faces × 4 squares × 2 triangles, outward normals sum to zero.
    f = m.boundary_faces
    assert len(f) == 48
    p = m.points_mm
    normals = np.cross(p[f[:, 1]] - p[f[:, 0]], p[f[:, 2]] - p[f[:, 0]])
    np.testing.assert_allclose(normals.sum(axis=0), 0, atol=1e-12)
    centre_out = ((p[f].mean(axis=1) - 0.5) * normals).sum(axis=1)
    assert (centre_out > 0).all()


def test_face_vertices_point_outwards():
    p = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]])
    for i, face in enumerate(FACE_VERTICES):
        n = np.cross(p[face[1]] - p[face[0]], p[face[2]] - p[face[0]])
        assert np.dot(n, p[face[0]] - p[i]) > 0


def test_inverted_and_degenerate_cells_are_named():
    p = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0], [1, 1, 0]])
    m = TetMesh(p, [[0, 1, 2, 3], [0, 2, 1, 3], [0, 1, 4, 2]])
    inverted, degenerate = m.bad_cells()
    assert inverted.tolist() == [1] and degenerate.tolist() == [2]
    with pytest.raises(MeshError, match="degenerate"):
        m.check_cells()
    m2 = TetMesh(p, [[0, 1, 2, 3], [0, 2, 1, 3]])
    with pytest.raises(MeshError, match=r"1 inverted.*fix-orientation"):
        m2.check_cells()
    m2.with_fixed_orientation().check_cells()


def test_nan_points_and_bad_shapes_are_refused():
    with pytest.raises(MeshError, match="NaN"):
        TetMesh(np.array([[0, 0, np.nan], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]]), [[0, 1, 2, 3]])
    with pytest.raises(MeshError, match="shape"):
        TetMesh(np.zeros((4, 2)), [[0, 1, 2, 3]])
    with pytest.raises(MeshError, match="no tetrahedra"):
        TetMesh(np.zeros((4, 3)), np.zeros((0, 4), int))
    with pytest.raises(MeshError, match="vertex ids"):
        TetMesh(np.zeros((4, 3)), [[0, 1, 2, 9]])


def test_topology_mismatch_names_first_cell():
    m = box_mesh([0, 0, 0], [1, 1, 1], (1, 1, 1))
    other = TetMesh(m.points_mm, m.tets[[1, 0, 2, 3, 4, 5]])
    with pytest.raises(TopologyMismatchError, match="tetrahedron 0 differs"):
        m.same_topology(other)
    with pytest.raises(TopologyMismatchError, match="points"):
        m.moved(m.points_mm[:-1])


def test_signed_volume_formula():
    p = np.array([[0, 0, 0], [2, 0, 0], [0, 3, 0], [0, 0, 4.0]])
    assert signed_volumes_mm3(p, np.array([[0, 1, 2, 3]]))[0] == pytest.approx(4.0)


def test_compact_points_drops_unused_points_and_keeps_geometry():
    """Unused points (spread among the used ones) go; every cell keeps its corner coordinates
    and signed volume; the kept ids index per-point data; the points' order is kept."""
    mesh = box_mesh([0, 0, 0], [6, 4, 2], (3, 2, 1))
    rng = np.random.default_rng(3)
    extra = rng.uniform(-5, 5, (7, 3))
    order = rng.permutation(mesh.n_points + len(extra))  # position of each point in the file
    points = np.empty((len(order), 3))
    points[order] = np.concatenate([mesh.points_mm, extra])
    tets = order[mesh.tets]
    kept, cells, ids = compact_points(points, tets)
    assert len(kept) == mesh.n_points and cells.dtype == np.intp and np.all(np.diff(ids) > 0)
    np.testing.assert_array_equal(kept[cells], points[tets])
    np.testing.assert_array_equal(kept, points[ids])
    np.testing.assert_allclose(signed_volumes_mm3(kept, cells), mesh.signed_volumes_mm3)
