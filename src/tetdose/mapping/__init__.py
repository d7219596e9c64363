"""Density mapping: CT → one density per mesh vertex, linear inside each tetrahedron (paper §II).

1. HU → density with a calibration (eq. 1, piecewise linear);
2. exact tetrahedron ∩ voxel volumes and barycentric moments (eq. 6–7, :mod:`.overlap`);
3. vertex densities (eq. 8–9 least squares, or the mass-conserving L2 projection, :mod:`.solve`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import maximum_filter, minimum_filter

from tetdose._typing import FloatArray
from tetdose.calibration import HUCalibration
from tetdose.image import Image
from tetdose.mapping.overlap import Overlap, compute_overlap, warn_if_uncovered
from tetdose.mapping.solve import project_l2, solve_lsq
from tetdose.mesh import TetMesh

SOLVERS = ("l2", "lsq")


@dataclass(frozen=True, eq=False)
class DensityMap:
    """Result of :func:`map_density`.

    ``mesh`` carries point_data ``density`` [g/cm³] and cell_data ``mass_g`` (mesh mass per
    tetrahedron, eq. 3) and ``ct_mass_g`` (CT mass inside it, eq. 4); for a region-split mapping it
    is the split mesh (vertices duplicated per region).
    """

    mesh: TetMesh
    overlap: Overlap
    solver: str
    ct_mass_covered_g: float  # CT mass inside the mesh: Σ_kj Vol(I_kj) ρ(V_j)
    outside_fraction: float  # fraction of the mesh volume outside the CT

    @property
    def density_g_cm3(self) -> FloatArray:
        return np.asarray(self.mesh.point_data["density"])

    @property
    def mesh_mass_g(self) -> float:
        """Eq. (22): Σ_k Vol(T_k)·mean vertex density."""
        return float(np.sum(self.mesh.cell_data["mass_g"]))

    @property
    def mass_error_covered(self) -> float:
        """Relative difference of the mesh mass and the CT mass it covers (solver's own error)."""
        return abs(self.mesh_mass_g - self.ct_mass_covered_g) / self.ct_mass_covered_g


def tet_masses_g(mesh: TetMesh, density_g_cm3: FloatArray) -> FloatArray:
    """Eq. (3): m(T_k) = ¼ Vol(T_k) Σ ρ(vertices) [g] (volumes in mm³)."""
    return mesh.volumes_mm3 * density_g_cm3[mesh.tets].mean(axis=1) / 1000.0


def map_density(mesh: TetMesh, ct_hu: Image, *, calibration: HUCalibration | None = None,
                solver: str = "l2", overlap: str = "exact", n_samples: int = 1000, seed: int = 0,
                by_region: bool = False, progress: bool = False) -> DensityMap:
    """Map a CT (HU) onto vertex densities [g/cm³] of ``mesh``.

    Parameters
    ----------
    solver : "l2" (default) mass-conserving L2 projection kept within the local range of the CT
        densities (no over/undershoot at edges), or "lsq" the paper's least squares of eq. (9).
    overlap : "exact" (default) clipped volumes, or "monte-carlo" the paper's hit-and-miss
        estimate with ``n_samples`` points per tetrahedron.
    by_region : duplicate vertices per region label so the density may jump across regions.

    A tetrahedron partly outside the CT gets the mean density of its covered part over its whole
    volume (a warning gives the uncovered fraction); one wholly outside all voxels is an error.
    """
    if solver not in SOLVERS:
        raise ValueError(f"solver must be one of {SOLVERS}, got {solver!r}")
    calibration = calibration or HUCalibration.schneider2000()
    mesh.check_cells()
    if by_region:
        mesh = mesh.split_by_region()
    ov = compute_overlap(mesh, ct_hu.grid, method=overlap, n_samples=n_samples, seed=seed,
                         progress=progress)
    outside = warn_if_uncovered(mesh, ov)
    rho_vox = calibration.density(ct_hu.array).ravel()
    pair_rho = rho_vox[ov.voxel]
    covered = ov.covered_volume_per_tet_mm3()
    ct_mass_tet = np.bincount(ov.tet, weights=ov.volume_mm3 * pair_rho,
                              minlength=mesh.n_tets) / 1000.0
    tet_mean = np.divide(ct_mass_tet * 1000.0, covered, out=np.zeros(mesh.n_tets),
                         where=covered > 0)
    if solver == "lsq":
        density = solve_lsq(mesh, tet_mean)
    else:
        corner = ov.bary_mm3 * pair_rho[:, None]
        rhs = np.bincount(mesh.tets[ov.tet].ravel(), weights=corner.ravel(),
                          minlength=mesh.n_points)
        # Uncovered parts of tetrahedra are filled with their tetrahedron's covered mean.
        gap = (mesh.volumes_mm3 - covered).clip(min=0.0) * tet_mean / 4.0
        rhs += np.bincount(mesh.tets.ravel(), weights=np.repeat(gap, 4), minlength=mesh.n_points)
        bounds = _vertex_bounds(mesh, ov, pair_rho, ct_hu.with_array(rho_vox.reshape(
            ct_hu.grid.shape)))
        density = project_l2(mesh, rhs, bounds=bounds)
    out = mesh.with_data(point_data={"density": density},
                         cell_data={"mass_g": tet_masses_g(mesh, density),
                                    "ct_mass_g": ct_mass_tet})
    return DensityMap(out, ov, solver, float(ct_mass_tet.sum()), outside)


def _vertex_bounds(mesh: TetMesh, ov: Overlap, pair_rho: FloatArray, rho_ct: Image
                   ) -> tuple[FloatArray, FloatArray]:
    """Admissible range of each vertex density [g/cm³]: the densities of the voxels its
    tetrahedra touch, widened by the 3×3×3 voxels around the vertex itself.

    The patch alone is too narrow on the mesh boundary, where a linear field's vertex value lies
    beyond every voxel centre inside the mesh; the neighbourhood brackets it.
    """
    lo = np.full(mesh.n_points, np.inf)
    hi = np.full(mesh.n_points, -np.inf)
    corners = mesh.tets[ov.tet]
    for a in range(4):
        np.minimum.at(lo, corners[:, a], pair_rho)
        np.maximum.at(hi, corners[:, a], pair_rho)
    idx = np.rint(rho_ct.grid.physical_to_index(mesh.points_mm)).astype(np.int64)
    inside = np.all((idx >= 0) & (idx < np.array(rho_ct.grid.size)), axis=1)
    flat = (idx[inside, 2] * rho_ct.grid.size[1] + idx[inside, 1]) * rho_ct.grid.size[0] \
        + idx[inside, 0]
    lo[inside] = np.minimum(lo[inside], minimum_filter(rho_ct.array, 3, mode="nearest").ravel()[flat])
    hi[inside] = np.maximum(hi[inside], maximum_filter(rho_ct.array, 3, mode="nearest").ravel()[flat])
    unknown = ~np.isfinite(lo)  # vertices whose tetrahedra all lie outside the CT
    lo[unknown], hi[unknown] = 0.0, np.inf
    return lo, hi


__all__ = ["DensityMap", "Overlap", "SOLVERS", "compute_overlap", "map_density", "tet_masses_g"]
