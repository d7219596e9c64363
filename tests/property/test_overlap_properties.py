"""Property tests (hypothesis) of the exact overlap, the mapping and the virtual CT.

- Partition of a tetrahedron: for any affine image of the reference tetrahedron lying inside the
  grid, Σ_j Vol(T ∩ V_j) = Vol(T) = |det A| / 6, and Σ_j ∫_{T∩V_j} λ_a = Vol(T) / 4 per vertex
  (the barycentric moments), on grids with any spacing and a rotated direction matrix.
- Vertex order: permuting a tetrahedron's four vertices permutes its barycentric moments the
  same way and leaves every overlap volume unchanged; relabelling the mesh's points permutes the
  mapped vertex densities.
- Mass: the mass-conserving mapping keeps the CT mass inside the mesh (1e-9), and voxelizing any
  mapped density (partial volume, zero background) keeps the mesh mass (eq. 14–15 exact).
"""

from __future__ import annotations

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tetdose.core.image import Image, ImageGrid
from tetdose.core.mesh import TetMesh
from tetdose.core.overlap import compute_overlap
from tetdose.core.voxelize import voxelize
from tetdose.mapping import map_density

from helpers import MILLI, box_mesh

PROPS = settings(derandomize=True, max_examples=30, deadline=None,
                 suppress_health_check=[HealthCheck.too_slow])
REF_TET = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
seeds = st.integers(min_value=0, max_value=2**32 - 1)


def rotation(rng: np.random.Generator) -> np.ndarray:
    """A uniformly random proper rotation (QR of a Gaussian matrix, signs fixed)."""
    q, r = np.linalg.qr(rng.standard_normal((3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def random_grid(rng: np.random.Generator, rotated: bool) -> ImageGrid:
    spacing = rng.uniform(0.5, 2.5, 3)
    size = tuple(int(n) for n in rng.integers(6, 14, 3))
    direction = rotation(rng) if rotated else np.eye(3)
    return ImageGrid(rng.uniform(-50, 50, 3), spacing, direction, size)


def affine_tet_inside(rng: np.random.Generator, grid: ImageGrid) -> tuple[np.ndarray, float]:
    """Vertices (4, 3) [mm] of A·REF_TET + b inside ``grid``, and |det A| / 6 (its volume)."""
    lo, hi = grid.bounds_grid_frame()
    while True:
        a = rng.standard_normal((3, 3)) * rng.uniform(0.2, 1.0) * (hi - lo).min()
        if abs(np.linalg.det(a)) > 1e-3 * np.linalg.norm(a) ** 3:
            break
    q = REF_TET @ a.T
    span = q.max(axis=0) - q.min(axis=0)
    scale = min(1.0, 0.95 * float(np.min((hi - lo) / span)))  # shrink to fit the grid box
    a, q = a * scale, q * scale
    shift = rng.uniform(lo - q.min(axis=0), hi - q.max(axis=0))
    q = q + shift
    return grid.origin_mm + q @ grid.direction.T, abs(np.linalg.det(a)) / 6.0


@PROPS
@given(seed=seeds, rotated=st.booleans())
def test_voxel_pieces_partition_an_affine_tetrahedron(seed: int, rotated: bool) -> None:
    rng = np.random.default_rng(seed)
    grid = random_grid(rng, rotated)
    pts, volume = affine_tet_inside(rng, grid)
    mesh = TetMesh(pts, np.array([[0, 1, 2, 3]])).with_fixed_orientation()
    ov = compute_overlap(mesh, grid)
    assert np.isclose(ov.volume_mm3.sum(), volume, rtol=1e-10, atol=0)
    assert np.all(ov.volume_mm3 > 0)
    np.testing.assert_allclose(ov.bary_mm3.sum(axis=0), volume / 4.0, rtol=1e-9)
    assert len(np.unique(ov.voxel)) == ov.n_pairs  # one entry per voxel


@PROPS
@given(seed=seeds, perm=st.permutations(range(4)))
def test_vertex_order_permutes_moments_and_keeps_volumes(seed: int, perm: list[int]) -> None:
    rng = np.random.default_rng(seed)
    grid = random_grid(rng, rotated=True)
    pts, _ = affine_tet_inside(rng, grid)
    # compute_overlap does not need positive orientation, so any vertex order is a valid input.
    mesh_a = TetMesh(pts, np.array([[0, 1, 2, 3]]))
    mesh_b = TetMesh(pts, np.array([perm]))
    a, b = compute_overlap(mesh_a, grid), compute_overlap(mesh_b, grid)
    tol = 1e-12 * mesh_a.volumes_mm3[0]
    va, vb = a.volume_matrix_mm3().toarray(), b.volume_matrix_mm3().toarray()
    assert np.abs(va - vb).max() <= tol
    # Moments are per vertex *id*: scatter both onto point ids and compare voxel by voxel.
    def by_point(ov, tets):  # noqa: ANN001, ANN202
        out = np.zeros((grid.n_voxels, 4))
        for slot in range(4):
            out[ov.voxel, tets[0, slot]] = ov.bary_mm3[:, slot]
        return out
    assert np.abs(by_point(a, mesh_a.tets) - by_point(b, mesh_b.tets)).max() <= tol


def _random_case(seed: int) -> tuple[TetMesh, Image]:
    """A jittered box mesh strictly inside a grid, and a random density CT (MILLI HU)."""
    rng = np.random.default_rng(seed)
    spacing = rng.uniform(1.0, 3.0, 3)
    size = tuple(int(n) for n in rng.integers(5, 9, 3))
    grid = ImageGrid(rng.uniform(-20, 20, 3), spacing, rotation(rng), size)
    lo, hi = grid.bounds_grid_frame()
    margin = rng.uniform(0.0, 0.3, 3) * (hi - lo)
    cells = tuple(int(n) for n in rng.integers(1, 4, 3))
    local = box_mesh(lo + margin / 2, hi - margin / 2, cells, jitter=0.2, seed=seed)
    mesh = local.moved(grid.origin_mm + local.points_mm @ grid.direction.T)
    density = rng.uniform(0.05, 2.0, grid.shape)
    return mesh, Image(density * 1000.0, grid)


@PROPS
@given(seed=seeds, solver=st.sampled_from(["l2", "lsq"]))
def test_voxelize_of_mapping_preserves_mass(seed: int, solver: str) -> None:
    mesh, ct = _random_case(seed)
    dm = map_density(mesh, ct, calibration=MILLI, solver=solver)
    assert dm.outside_fraction < 1e-12  # mesh inside the grid
    if solver == "l2":
        assert dm.mass_error_covered < 1e-9
    img = voxelize(dm.mesh, dm.density_g_cm3, ct.grid, background=0.0, overlap=dm.overlap)
    image_mass_g = img.array.sum() * ct.grid.voxel_volume_mm3 / 1000.0
    assert np.isclose(image_mass_g, dm.mesh_mass_g, rtol=1e-10, atol=0)


@settings(derandomize=True, max_examples=10, deadline=None)
@given(seed=seeds, solver=st.sampled_from(["l2", "lsq"]))
def test_point_relabelling_permutes_the_vertex_densities(seed: int, solver: str) -> None:
    mesh, ct = _random_case(seed)
    perm = np.random.default_rng(seed + 1).permutation(mesh.n_points)  # new id -> old id
    inverse = np.argsort(perm)
    relabelled = TetMesh(mesh.points_mm[perm], inverse[mesh.tets])
    a = map_density(mesh, ct, calibration=MILLI, solver=solver).density_g_cm3
    b = map_density(relabelled, ct, calibration=MILLI, solver=solver).density_g_cm3
    np.testing.assert_allclose(b, a[perm], rtol=1e-8, atol=1e-10)
