"""A voxel dose put on tets by energy (tetdose.coupling.onto_mesh): energy conserved against sums
that do not use the overlap, a uniform dose stays uniform, a grid that misses the mesh is refused."""

import numpy as np
import pytest

from tetdose._constants import G_PER_KG, J_PER_MEV, MM3_PER_CM3
from tetdose.core.image import Image, ImageGrid
from tetdose.coupling.onto_mesh import result_onto_mesh, voxel_dose_onto_mesh
from tetdose.errors import GeometryMismatchError
from tetdose.transport.history.result import DoseResult

from helpers import box_mesh, grid_for


def _random_image(grid, lo, hi, seed):
    rng = np.random.default_rng(seed)
    return Image(rng.uniform(lo, hi, grid.shape), grid)


def _voxel_energy_j(dose, density):
    """E_v = D_v ρ_v V_v [J] of every voxel (no overlap involved)."""
    mass_kg = density.array * density.grid.voxel_volume_mm3 / MM3_PER_CM3 / G_PER_KG
    return dose.array * mass_kg


def test_energy_of_the_covered_voxels_lands_on_the_tets():
    # grid 10 × 8 × 6 voxels of 2.5 × 3 × 4 mm; the mesh fills voxels 2..7 × 1..6 × 1..5 exactly
    # (its outer faces are voxel faces), its interior points are jittered so tets cut voxels.
    grid = grid_for([0, 0, 0], [25, 24, 24], [2.5, 3.0, 4.0])
    mesh = box_mesh([5.0, 3.0, 4.0], [17.5, 18.0, 20.0], (4, 3, 3), jitter=0.3, seed=1)
    dose = _random_image(grid, 0.0, 2.0, 1)
    density = _random_image(grid, 0.2, 1.9, 2)
    dose_k, energy_k = voxel_dose_onto_mesh(dose, density, mesh)
    inside = _voxel_energy_j(dose, density)[1:5, 1:6, 2:7].sum()
    assert energy_k.sum() == pytest.approx(inside, rel=1e-12, abs=0)
    assert np.all(dose_k >= 0.0) and np.all(dose_k <= 2.0 + 1e-12)


def test_a_uniform_dose_stays_uniform_on_a_tilted_grid():
    direction = np.linalg.qr(np.random.default_rng(3).normal(size=(3, 3)))[0]
    direction *= np.sign(np.linalg.det(direction))
    grid = ImageGrid([-30.0, -30.0, -30.0] @ direction.T, [3.0, 3.0, 3.0], direction, (20, 20, 20))
    mesh = box_mesh([-8, -7, -6], [7, 8, 9], (3, 3, 3), jitter=0.25, seed=4)
    density = _random_image(grid, 0.1, 2.0, 5)
    dose = Image(np.full(grid.shape, 1.7), grid)
    dose_k, energy_k = voxel_dose_onto_mesh(dose, density, mesh)
    np.testing.assert_allclose(dose_k, 1.7, rtol=1e-13)
    # uniform density too: E = D ρ Vol(mesh), the mesh volume from its own tets
    uniform = Image(np.full(grid.shape, 0.8), grid)
    _, energy_k = voxel_dose_onto_mesh(dose, uniform, mesh)
    expected = 1.7 * 0.8 * mesh.volumes_mm3.sum() / MM3_PER_CM3 / G_PER_KG
    assert energy_k.sum() == pytest.approx(expected, rel=1e-12)


def test_tets_in_vacuum_voxels_get_zero_dose():
    grid = grid_for([0, 0, 0], [12, 12, 12], [2.0, 2.0, 2.0])
    mesh = box_mesh([2, 2, 2], [10, 10, 10], (2, 2, 2))
    density = Image(np.zeros(grid.shape), grid)
    dose_k, energy_k = voxel_dose_onto_mesh(Image(np.ones(grid.shape), grid), density, mesh)
    assert not dose_k.any() and not energy_k.any()


def test_a_grid_that_does_not_cover_the_mesh_is_refused():
    grid = grid_for([0, 0, 0], [10, 10, 10], [2.0, 2.0, 2.0])
    mesh = box_mesh([4, 4, 4], [12, 8, 8], (2, 1, 1))
    ones = Image(np.ones(grid.shape), grid)
    with pytest.raises(GeometryMismatchError, match="does not cover the mesh"):
        voxel_dose_onto_mesh(ones, ones, mesh)
    other = grid_for([0, 0, 0], [10, 10, 12], [2.0, 2.0, 2.0])
    with pytest.raises(GeometryMismatchError, match="not on the same grid"):
        voxel_dose_onto_mesh(ones, Image(np.ones(other.shape), other), box_mesh([2] * 3, [8] * 3,
                                                                               (1, 1, 1)))


def test_result_rows_on_the_mesh_match_the_image_map_and_conserve_each_batch():
    grid = grid_for([0, 0, 0], [16, 16, 16], [2.0, 2.0, 2.0])
    mesh = box_mesh([2, 2, 2], [14, 14, 14], (3, 3, 3), jitter=0.3, seed=6)
    density = _random_image(grid, 0.3, 1.5, 7)
    rng = np.random.default_rng(8)
    batches, n_vox = 4, grid.n_voxels
    energy = rng.uniform(0.0, 1.0, (batches, n_vox))
    mass_g = density.array.ravel() * grid.voxel_volume_mm3 / MM3_PER_CM3
    voxel = DoseResult(energy, np.full(batches, 250), mass_g, np.zeros((batches, 5)),
                       np.zeros((batches, 7), dtype=np.int64), 1.0, 1, "analog", "voxel", 0.0,
                       "test", grid)
    on_mesh = result_onto_mesh(voxel, density, mesh)
    assert on_mesh.geometry == "mesh" and on_mesh.n_tets == mesh.n_tets
    dose_k, energy_k = voxel_dose_onto_mesh(voxel.to_images()[0], density, mesh)
    np.testing.assert_allclose(on_mesh.dose_gy, dose_k, rtol=1e-12)
    inside = energy.reshape(batches, *grid.shape)[:, 1:7, 1:7, 1:7].sum(axis=(1, 2, 3))
    np.testing.assert_allclose(on_mesh.energy_per_batch_mev.sum(axis=1), inside, rtol=1e-12)
    # per-particle energy [MeV] and J agree through the dose: E_k = D_k m_k
    np.testing.assert_allclose(energy_k, on_mesh.energy_mev * J_PER_MEV, rtol=1e-12)
    assert np.all(on_mesh.dose_std_gy > 0)
