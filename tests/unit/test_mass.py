"""tetdose.core.mass: tet masses (eq. 3) and overlap-pair masses (eq. 14–15) agree and conserve."""

import numpy as np
import pytest

from tetdose.core.image import ImageGrid
from tetdose.core.mass import mass_g, pair_mass_g, tet_mass_g
from tetdose.core.mesh import TetMesh
from tetdose.core.overlap import compute_overlap
from tetdose.errors import DensityError


def _tet(scale: float = 1.0) -> TetMesh:
    pts = scale * np.array([[0.3, 0.2, 0.1], [4.1, 0.4, 0.3], [0.2, 3.7, 0.5], [0.5, 0.1, 4.4]])
    return TetMesh(pts + 1.0, np.array([[0, 1, 2, 3]]))


def test_tet_mass_is_the_integral_of_a_linear_density():
    """∫_T ρ dV of a linear ρ = volume × ρ(centroid) = volume × mean of vertex values."""
    mesh = _tet()
    rho = 1.0 + 0.05 * mesh.points_mm @ np.array([1.0, -2.0, 0.5])
    centroid_rho = 1.0 + 0.05 * mesh.points_mm.mean(axis=0) @ np.array([1.0, -2.0, 0.5])
    expected = mesh.volumes_mm3[0] * centroid_rho / 1000.0
    np.testing.assert_allclose(tet_mass_g(mesh, rho), [expected], rtol=1e-13)
    np.testing.assert_allclose(mass_g(1000.0, 1.2), 1.2)


def test_pair_masses_sum_to_the_tet_mass_inside_the_grid():
    mesh = _tet()
    rho = np.array([1.0, 1.5, 0.3, 2.0])
    grid = ImageGrid((0.0, 0.0, 0.0), (1.0, 1.3, 0.9), np.eye(3), (8, 7, 9))
    ov = compute_overlap(mesh, grid)
    per_tet = np.bincount(ov.tet, weights=pair_mass_g(mesh, ov, rho), minlength=1)
    np.testing.assert_allclose(per_tet, tet_mass_g(mesh, rho), rtol=1e-12)


def test_missing_or_misshaped_density_is_a_density_error():
    with pytest.raises(DensityError, match="point_data 'density'"):
        tet_mass_g(_tet())
    with pytest.raises(DensityError, match="one value per mesh point"):
        tet_mass_g(_tet(), np.ones(3))
