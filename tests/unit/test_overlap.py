"""Exact tetrahedron ∩ voxel volumes against exact cases and an independent Monte Carlo estimate."""

import numpy as np
import pytest

from tetdose.core.image import ImageGrid
from tetdose.core.mesh import TetMesh
from tetdose.core.overlap import compute_overlap
from tetdose.errors import GeometryMismatchError

from helpers import box_mesh, grid_for


def random_tets(n, lo, hi, seed):
    rng = np.random.default_rng(seed)
    pts = rng.uniform(lo, hi, (4 * n, 3))
    return TetMesh(pts, np.arange(4 * n).reshape(n, 4)).with_fixed_orientation()


GRID = ImageGrid([0.5, 0.75, 1.0], [1.0, 1.5, 2.0], np.eye(3), (14, 12, 9))


def test_rows_sum_to_tet_volume_for_tets_inside_grid():
    mesh = random_tets(60, [1, 1, 1], [13, 17, 17], seed=1)
    ov = compute_overlap(mesh, GRID)
    np.testing.assert_allclose(ov.covered_volume_per_tet_mm3(), mesh.volumes_mm3, rtol=1e-12)
    # Barycentric moments: ∫_T λ_a = V/4 for each vertex.
    per_vertex = np.zeros((mesh.n_tets, 4))
    np.add.at(per_vertex, ov.tet, ov.bary_mm3)
    np.testing.assert_allclose(per_vertex, np.repeat(mesh.volumes_mm3[:, None] / 4, 4, 1),
                               rtol=1e-11)


def test_exact_agrees_with_monte_carlo_within_its_statistical_error():
    mesh = random_tets(5, [1, 1, 1], [13, 17, 17], seed=2)
    n = 200_000
    exact = compute_overlap(mesh, GRID).volume_matrix_mm3().toarray()
    mc = compute_overlap(mesh, GRID, method="monte-carlo", n_samples=n, seed=3)
    mc = mc.volume_matrix_mm3().toarray()
    f_exact = exact / mesh.volumes_mm3[:, None]
    f_mc = mc / mesh.volumes_mm3[:, None]
    sigma = np.sqrt(f_exact * (1 - f_exact) / n) + 1e-12
    z = np.abs(f_mc - f_exact) / sigma
    assert z.max() < 5.0
    assert np.all((f_exact > 0) | (f_mc == 0))  # MC never hits a voxel the exact method misses


def test_invariant_to_vertex_order():
    mesh = random_tets(20, [1, 1, 1], [13, 17, 17], seed=4)
    rng = np.random.default_rng(5)
    perm = np.array([rng.permutation(4) for _ in range(mesh.n_tets)])
    shuffled = TetMesh(mesh.points_mm, np.take_along_axis(mesh.tets, perm, 1))
    a = compute_overlap(mesh, GRID).volume_matrix_mm3()
    b = compute_overlap(shuffled, GRID).volume_matrix_mm3()
    assert abs(a - b).max() < 1e-12 * mesh.volumes_mm3.max()


def test_tet_smaller_than_a_voxel_lies_in_one_voxel():
    p = np.array([[3.1, 4.1, 5.1], [3.3, 4.1, 5.1], [3.1, 4.4, 5.1], [3.1, 4.1, 5.5]])
    mesh = TetMesh(p, [[0, 1, 2, 3]])
    grid = ImageGrid([0, 0, 0], [1, 1, 1], np.eye(3), (10, 10, 10))
    ov = compute_overlap(mesh, grid)
    assert ov.n_pairs == 1 and ov.voxel[0] == (5 * 10 + 4) * 10 + 3
    np.testing.assert_allclose(ov.volume_mm3, mesh.volumes_mm3, rtol=1e-14)


def test_faces_on_voxel_planes_and_vertices_on_corners():
    """A box meshed exactly on voxel planes: every voxel fully covered, no spurious pairs."""
    grid = grid_for([0, 0, 0], [4, 6, 8], [1, 2, 2])
    mesh = box_mesh([0, 0, 0], [4, 6, 8], (4, 3, 4))  # vertices exactly on voxel corners
    ov = compute_overlap(mesh, grid)
    cover = ov.covered_volume_per_voxel_mm3()
    np.testing.assert_allclose(cover, grid.voxel_volume_mm3, rtol=1e-12)
    assert ov.n_pairs == mesh.n_tets  # each tet inside exactly one voxel: no zero-volume pairs


def test_rotated_grid_direction_is_honoured():
    """Rotating mesh and grid together leaves the overlap matrix unchanged."""
    angle = 0.4
    rot = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0],
                    [0, 0, 1.0]]) @ np.array([[1, 0, 0], [0, 0, -1.0], [0, 1, 0]])
    mesh = random_tets(15, [1, 1, 1], [13, 17, 17], seed=6)
    a = compute_overlap(mesh, GRID).volume_matrix_mm3()
    shift = np.array([10.0, -20.0, 5.0])
    moved = TetMesh((mesh.points_mm - GRID.origin_mm) @ rot.T + GRID.origin_mm + shift,
                    mesh.tets)
    grid2 = ImageGrid(GRID.origin_mm + shift, GRID.spacing_mm, rot, GRID.size)
    b = compute_overlap(moved, grid2).volume_matrix_mm3()
    assert abs(a - b).max() < 1e-10


def test_parts_outside_the_grid_are_not_counted():
    grid = ImageGrid([0, 0, 0], [1, 1, 1], np.eye(3), (4, 4, 4))  # covers [-0.5, 3.5]^3
    mesh = box_mesh([1.5, 1.5, 1.5], [5.5, 5.5, 5.5], (2, 2, 2))
    ov = compute_overlap(mesh, grid)
    assert ov.covered_volume_per_tet_mm3().sum() == pytest.approx(8.0, rel=1e-12)


def test_mesh_wholly_outside_is_an_error():
    grid = ImageGrid([0, 0, 0], [1, 1, 1], np.eye(3), (4, 4, 4))
    mesh = box_mesh([10, 10, 10], [12, 12, 12], (1, 1, 1))
    with pytest.raises(GeometryMismatchError, match="wholly outside"):
        compute_overlap(mesh, grid)


def test_chunking_gives_the_same_matrix():
    mesh = random_tets(40, [1, 1, 1], [13, 17, 17], seed=7)
    a = compute_overlap(mesh, GRID).volume_matrix_mm3()
    b = compute_overlap(mesh, GRID, chunk_pairs=50).volume_matrix_mm3()
    assert abs(a - b).max() == 0.0
