"""Mesh ↔ voxel-grid transfer of dose, conserving deposited energy; point location in a mesh.

The neutral foundation of comparison (:mod:`tetdose.compare`), accumulation
(:mod:`tetdose.dose.accumulate`) and the 4D dose (:mod:`tetdose.dose.dose4d`): it imports only the mesh,
the image, the overlap and the masses, never those modules.

Both directions go through the exact tet ∩ voxel overlap (:mod:`tetdose.core.overlap`). With
the vertex density ρ linear in each tetrahedron, the mass of tet k inside voxel j is

    m_kj = Σ_a ρ_a ∫_{T_k ∩ V_j} λ_a dV          (the paper's eq. 14–15, exact)

and m_k = Σ_j m_kj = Vol(T_k)·(Σ_a ρ_a)/4 for a tet inside the grid. Dose is energy per mass, so
energy E = D·m is what is moved, split in proportion to mass:

    mesh → voxel:  E_j = Σ_k E_k · m_kj / m_k  = Σ_k D_k m_kj,       D_j = E_j / m_j
    voxel → mesh:  E_k = Σ_j E_j · m_kj / m_j,                      D_k = E_k / m_k

with m_j = Σ_k m_kj the mesh mass in voxel j. The two maps are adjoint: Σ_j E_j =
Σ_k E_k for the covered part, so a mesh → voxel → mesh round trip conserves energy to round-off.
Without a density (``density_g_cm3=None`` and no point_data ``density``) unit density is used,
i.e. volume weighting. Voxels and tets that receive no mass get dose 0.

Point location (:func:`locate_points`) bins tetrahedra by their bounding boxes on a uniform bucket
grid, then tests the candidates of each point's bucket with barycentric coordinates, all in numpy.
"""

from __future__ import annotations

import numpy as np

from tetdose._typing import FloatArray, IntArray
from tetdose.core import _locate_kernels
from tetdose.core.image import Image, ImageGrid
from tetdose.core.mass import pair_mass_g
from tetdose.core.mesh import TetMesh
from tetdose.core.overlap import Overlap, compute_overlap
from tetdose.errors import DensityError, DoseError, GeometryMismatchError, ImageError

#: A point counts as inside a tetrahedron when its smallest barycentric coordinate is ≥ −this.
INSIDE_TOL = 1e-9


def vertex_density(mesh: TetMesh, density_g_cm3: FloatArray | None) -> FloatArray:
    """The density to weight with: the argument, point_data ``density``, or 1 (volume weighting)."""
    if density_g_cm3 is None:
        density_g_cm3 = mesh.point_data.get("density", np.ones(mesh.n_points))
    rho = np.asarray(density_g_cm3, dtype=np.float64)
    if rho.shape != (mesh.n_points,):
        raise DensityError(f"density must have one value per mesh point ({mesh.n_points}), got "
                           f"shape {rho.shape}: pass the density of this mesh's points")
    return rho


def weighted_pair_mass_g(mesh: TetMesh, overlap: Overlap,
                         density_g_cm3: FloatArray | None = None) -> FloatArray:
    """(P,) mass m_kj [g] of each overlap pair (tet k, voxel j) with :func:`vertex_density`."""
    return pair_mass_g(mesh, overlap, vertex_density(mesh, density_g_cm3))


def _overlap_for(mesh: TetMesh, grid: ImageGrid, overlap: Overlap | None) -> Overlap:
    if overlap is None:
        return compute_overlap(mesh, grid)
    if overlap.n_tets != mesh.n_tets or not overlap.grid.same_as(grid):
        raise GeometryMismatchError("the overlap was computed for another mesh or grid; "
                                    "pass overlap=None to recompute it")
    return overlap


def _ratio(num: FloatArray, den: FloatArray) -> FloatArray:
    return np.divide(num, den, out=np.zeros_like(num), where=den > 0)


def mesh_dose_to_grid(mesh: TetMesh, dose_gy: FloatArray, grid: ImageGrid, *,
                      density_g_cm3: FloatArray | None = None, overlap: Overlap | None = None
                      ) -> Image:
    """Voxel dose [Gy] D_j = Σ_k D_k m_kj / Σ_k m_kj of a per-tet dose (module docstring)."""
    dose = per_tet_dose(mesh, dose_gy)
    ov = _overlap_for(mesh, grid, overlap)
    m_kj = weighted_pair_mass_g(mesh, ov, density_g_cm3)
    energy = np.bincount(ov.voxel, weights=dose[ov.tet] * m_kj, minlength=grid.n_voxels)
    mass = np.bincount(ov.voxel, weights=m_kj, minlength=grid.n_voxels)
    return Image(_ratio(energy, mass).reshape(grid.shape), grid)


def mesh_mass_on_grid(mesh: TetMesh, grid: ImageGrid, *, density_g_cm3: FloatArray | None = None,
                      overlap: Overlap | None = None) -> Image:
    """Mesh mass in each voxel [g], m_j = Σ_k m_kj (the voxel mass of the maps)."""
    ov = _overlap_for(mesh, grid, overlap)
    mass = np.bincount(ov.voxel, weights=weighted_pair_mass_g(mesh, ov, density_g_cm3),
                       minlength=grid.n_voxels)
    return Image(mass.reshape(grid.shape), grid)


def grid_dose_to_mesh(mesh: TetMesh, dose: Image, *, density_g_cm3: FloatArray | None = None,
                      overlap: Overlap | None = None) -> FloatArray:
    """Per-tet dose [Gy] D_k = Σ_j D_j m_kj / Σ_j m_kj of a voxel dose (module docstring).

    E_j m_kj / m_j = D_j m_kj whatever the voxel mass m_j, so only the mesh's share of each
    voxel's energy reaches the mesh; energy deposited outside the mesh stays outside.
    """
    grid = dose.grid
    ov = _overlap_for(mesh, grid, overlap)
    m_kj = weighted_pair_mass_g(mesh, ov, density_g_cm3)
    d_j = np.asarray(dose.array, dtype=np.float64).ravel()
    energy_k = np.bincount(ov.tet, weights=d_j[ov.voxel] * m_kj, minlength=mesh.n_tets)
    mass_k = np.bincount(ov.tet, weights=m_kj, minlength=mesh.n_tets)
    return _ratio(energy_k, mass_k)


def per_tet_dose(mesh: TetMesh, dose_gy: FloatArray) -> FloatArray:
    """``dose_gy`` as a float64 (M,) array, one value [Gy] per tetrahedron of ``mesh``."""
    dose = np.asarray(dose_gy, dtype=np.float64)
    if dose.shape != (mesh.n_tets,):
        raise DoseError(f"the dose has shape {dose.shape}, the mesh {mesh.n_tets} tetrahedra: "
                        "use the dose computed on this mesh")
    return dose


def locate_points(mesh: TetMesh, points_mm: FloatArray) -> tuple[IntArray, FloatArray]:
    """Tetrahedron containing each point (−1 outside the mesh) and its barycentric coordinates.

    Returns ``tet`` (P,) intp and ``bary`` (P, 4) (rows of −1 ids are zero). A point on a shared
    face (within :data:`INSIDE_TOL`) goes to the first candidate; both give the same position.
    """
    pts = np.ascontiguousarray(np.asarray(points_mm, dtype=np.float64).reshape(-1, 3))
    tet = np.empty(len(pts), dtype=np.intp)
    bary = np.zeros((len(pts), 4))
    p = mesh.points_mm[mesh.tets]
    inv = np.ascontiguousarray(np.linalg.inv(
        np.stack([p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]], axis=2)))
    b = _Buckets(p)
    _locate_kernels.locate(pts, b.lo, float(b.h), b.n.astype(np.int64), b.ptr,
                           b.tets.astype(np.intp), inv, np.ascontiguousarray(p[:, 0]),
                           INSIDE_TOL, tet, bary)
    return tet, bary


class _Buckets:
    """Uniform bucket grid over the mesh; each bucket lists the tets whose bounding box meets it."""

    def __init__(self, corners: FloatArray) -> None:
        lo, hi = corners.min(axis=1), corners.max(axis=1)
        self.lo = lo.min(axis=0)
        extent = hi.max(axis=0) - self.lo
        self.h = max(float(np.median((hi - lo).max(axis=1))), 1e-9 * float(extent.max()), 1e-12)
        self.n = np.maximum(np.ceil(extent / self.h).astype(np.int64), 1)
        a = self._cell(lo)
        b = self._cell(hi)
        span = b - a + 1
        count = span.prod(axis=1)
        owner = np.repeat(np.arange(len(corners)), count)
        rank = np.arange(int(count.sum())) - np.repeat(np.cumsum(count) - count, count)
        sy, sz = span[owner, 1], span[owner, 2]
        ijk = a[owner] + np.column_stack([rank // (sy * sz), (rank // sz) % sy, rank % sz])
        flat = self._flat(ijk)
        order = np.argsort(flat, kind="stable")
        self.tets = owner[order]
        self.ptr = np.zeros(int(self.n.prod()) + 1, dtype=np.int64)
        np.cumsum(np.bincount(flat, minlength=int(self.n.prod())), out=self.ptr[1:])

    def _cell(self, x: FloatArray) -> IntArray:
        return np.clip(np.floor((x - self.lo) / self.h).astype(np.int64), 0, self.n - 1)

    def _flat(self, ijk: IntArray) -> IntArray:
        return (ijk[:, 0] * self.n[1] + ijk[:, 1]) * self.n[2] + ijk[:, 2]


def interpolate_at_points(image: Image, points_mm: FloatArray, *, outside: float = np.nan
                          ) -> FloatArray:
    """Trilinear interpolation of ``image`` at patient points [mm].

    Between the outermost voxel centres and the image's outer faces the edge value is used
    (nearest); beyond the outer faces the result is ``outside``.
    """
    from scipy.ndimage import map_coordinates

    idx = image.grid.physical_to_index(np.asarray(points_mm, dtype=np.float64).reshape(-1, 3))
    size = np.array(image.grid.size)
    inside = np.all((idx >= -0.5) & (idx <= size - 0.5), axis=1)
    coords = np.clip(idx, 0, size - 1)[:, ::-1].T  # (k, j, i) for the (nz, ny, nx) array
    vals = map_coordinates(np.asarray(image.array, dtype=np.float64), coords, order=1,
                           mode="nearest")
    return np.where(inside, vals, outside)


def dose_on_grid(dose: tuple[TetMesh, FloatArray] | Image, grid: ImageGrid, *,
                 what: str = "the dose image") -> Image:
    """A dose on ``grid`` [its unit], negative values clipped to 0: a (mesh, per-tet dose) pair
    through :func:`mesh_dose_to_grid` (energy-conserving), or a dose image trilinearly
    (:func:`interpolate_at_points`, 0 outside it) unless it is on ``grid`` already."""
    if isinstance(dose, Image):
        if dose.array.ndim != 3:
            raise ImageError(f"{what} is not a 3-D dose image; give a 3-D dose (.nrrd, .mha …)")
        img = dose if dose.grid.same_as(grid) else Image(
            interpolate_at_points(dose, grid.voxel_centers_mm(), outside=0.0).reshape(grid.shape),
            grid)
    else:
        mesh, dose_gy = dose
        img = mesh_dose_to_grid(mesh, dose_gy, grid)
    return Image(np.clip(np.asarray(img.array, dtype=np.float64), 0.0, None), grid)
