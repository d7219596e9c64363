"""Mass [g] of tetrahedra and voxels from their volume [mm³] and density [g/cm³].

    m = V ρ / MM3_PER_CM3                         (one cell of uniform density)
    m(T_k) = ¼ Vol(T_k) Σ_a ρ_a / MM3_PER_CM3     (the paper's eq. 3: ρ linear in the tet)

The one place tetdose turns volumes and densities into masses: mapping, accumulation, the
transport world's cell masses, DVHs by mass and the metrics all call these.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from tetdose._constants import MM3_PER_CM3
from tetdose._typing import FloatArray
from tetdose.core.mesh import TetMesh
from tetdose.errors import DensityError

if TYPE_CHECKING:
    from tetdose.core.overlap import Overlap


def mass_g(volume_mm3: FloatArray | float, density_g_cm3: FloatArray | float) -> FloatArray:
    """m = V ρ / 1000: mass [g] of cells of volume [mm³] and uniform density [g/cm³]."""
    return np.asarray(volume_mm3, dtype=np.float64) * density_g_cm3 / MM3_PER_CM3


def tet_mass_g(mesh: TetMesh, density_g_cm3: FloatArray | None = None) -> FloatArray:
    """Eq. (3): m(T_k) = ¼ Vol(T_k) Σ_a ρ_a [g] with vertex densities ρ [g/cm³].

    ``density_g_cm3`` (one value per point) defaults to the mesh's point_data ``density``.
    """
    if density_g_cm3 is None:
        if "density" not in mesh.point_data:
            raise DensityError("the mesh has no point_data 'density' (g/cm³) for its tet masses: "
                               "map or deform it with densities first (tetdose map/deform)")
        density_g_cm3 = mesh.point_data["density"]
    rho = np.asarray(density_g_cm3, dtype=np.float64)
    if rho.shape != (mesh.n_points,):
        raise DensityError(f"density must have one value per mesh point ({mesh.n_points}), got "
                           f"shape {rho.shape}: pass the density of this mesh's points")
    return mass_g(mesh.volumes_mm3, rho[mesh.tets].mean(axis=1))


def pair_mass_g(mesh: TetMesh, overlap: Overlap, density_g_cm3: FloatArray) -> FloatArray:
    """(P,) mass m_kj [g] of each overlap pair (tet k, voxel j): eq. (14–15),
    m_kj = Σ_a ρ_a ∫_{T_k ∩ V_j} λ_a dV / 1000, exact for a density linear in each tet."""
    rho = np.asarray(density_g_cm3, dtype=np.float64)
    return np.einsum("pa,pa->p", rho[mesh.tets[overlap.tet]], overlap.bary_mm3) / MM3_PER_CM3
