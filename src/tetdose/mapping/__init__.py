"""Density mapping: CT → one density per mesh vertex, linear inside each tetrahedron (paper §II).

1. HU → density with a calibration (eq. 1, piecewise linear);
2. exact tetrahedron ∩ voxel volumes and barycentric moments (eq. 6–7, :mod:`.overlap`);
3. vertex densities (eq. 8–9 least squares, or the mass-conserving L2 projection, :mod:`.solve`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import maximum_filter, minimum_filter

from tetdose._constants import MM3_PER_CM3
from tetdose._typing import FloatArray
from tetdose.core.calibration import HUCalibration
from tetdose.core.image import Image, ImageGrid, check_ct_hu
from tetdose.core.mass import tet_mass_g
from tetdose.core.mesh import TetMesh
from tetdose.core.overlap import Overlap, compute_overlap, warn_if_uncovered
from tetdose.errors import OptionError
from tetdose.mapping.solve import SOLVERS, project_l2, solve_lsq


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
    A CT that cannot hold HU (:func:`tetdose.core.image.check_ct_hu`) is refused. Only "lsq" can
    return negative vertex densities (it undershoots at sharp edges, as the paper's method does).
    """
    if solver not in SOLVERS:
        raise OptionError(f"solver must be one of {SOLVERS}, got {solver!r}")
    check_ct_hu(ct_hu)
    calibration = calibration or HUCalibration.schneider2000()
    mesh.check_cells()
    if by_region:
        mesh = mesh.split_by_region()
    full_grid = ct_hu.grid
    ct_hu, crop_start = _crop_to_mesh(ct_hu, mesh)  # memory ∝ the mesh box, not the whole CT
    ov = compute_overlap(mesh, ct_hu.grid, method=overlap, n_samples=n_samples, seed=seed,
                         progress=progress)
    outside = warn_if_uncovered(mesh, ov)
    rho_vox = calibration.density_checked(ct_hu.array, "the CT around the mesh")[0].ravel()
    pair_rho = rho_vox[ov.voxel]
    covered = ov.covered_volume_per_tet_mm3()
    ct_mass_tet = np.bincount(ov.tet, weights=ov.volume_mm3 * pair_rho,
                              minlength=mesh.n_tets) / MM3_PER_CM3
    tet_mean = np.divide(ct_mass_tet * MM3_PER_CM3, covered, out=np.zeros(mesh.n_tets),
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
                         cell_data={"mass_g": tet_mass_g(mesh, density),
                                    "ct_mass_g": ct_mass_tet})
    return DensityMap(out, _on_full_grid(ov, full_grid, crop_start), solver,
                      float(ct_mass_tet.sum()), outside)


def _crop_to_mesh(ct: Image, mesh: TetMesh) -> tuple[Image, np.ndarray]:
    """The CT cropped to the voxels the mesh's bounding box can touch (+1 voxel), and the crop's
    first voxel index (i, j, k). A mesh wholly outside leaves the CT whole (the overlap says so)."""
    idx = ct.grid.physical_to_index(mesh.points_mm)
    size = np.array(ct.grid.size)
    lo = np.clip(np.floor(idx.min(axis=0)).astype(np.int64) - 1, 0, size - 1)
    hi = np.clip(np.ceil(idx.max(axis=0)).astype(np.int64) + 1, 0, size - 1)
    if np.any(idx.max(axis=0) < -0.5) or np.any(idx.min(axis=0) > size - 0.5):
        return ct, np.zeros(3, dtype=np.int64)
    arr = ct.array[lo[2]:hi[2] + 1, lo[1]:hi[1] + 1, lo[0]:hi[0] + 1]
    grid = ImageGrid(ct.grid.index_to_physical(lo.astype(np.float64)), ct.grid.spacing_mm,
                     ct.grid.direction, tuple(int(n) for n in hi - lo + 1))
    return Image(arr, grid), lo


def _on_full_grid(ov: Overlap, grid: ImageGrid, corner: np.ndarray) -> Overlap:
    """Re-express an overlap computed on a crop starting at voxel ``corner`` on the full grid."""
    if ov.grid.size == grid.size:
        return ov
    nx, ny, _ = ov.grid.size
    i, j, k = ov.voxel % nx, (ov.voxel // nx) % ny, ov.voxel // (nx * ny)
    fx, fy, _ = grid.size
    voxel = ((k + corner[2]) * fy + (j + corner[1])) * fx + (i + corner[0])
    return Overlap(grid, ov.tet_ptr, voxel, ov.bary_mm3, ov.method)


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
    voxel = rho_ct.grid.voxel_of(mesh.points_mm)
    inside = voxel >= 0
    flat = voxel[inside]
    lo[inside] = np.minimum(lo[inside], minimum_filter(rho_ct.array, 3, mode="nearest").ravel()[flat])
    hi[inside] = np.maximum(hi[inside], maximum_filter(rho_ct.array, 3, mode="nearest").ravel()[flat])
    unknown = ~np.isfinite(lo)  # vertices whose tetrahedra all lie outside the CT
    lo[unknown], hi[unknown] = 0.0, np.inf
    return lo, hi


__all__ = ["DensityMap", "Overlap", "SOLVERS", "compute_overlap", "map_density"]
