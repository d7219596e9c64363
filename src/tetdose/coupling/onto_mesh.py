"""A voxel dose put on the tetrahedra of a mesh by energy.

A voxel engine (ompmc, EGSnrc, Geant4 on a CT, tetdose's own voxel world) deposits energy in
voxels of uniform density ρ_v. The energy voxel v received is E_v = D_v · ρ_v · V_v; the part of it
in the space tet k occupies is split by the exact tet ∩ voxel overlap volume (the voxel is
uniform, so energy goes with volume):

    E_k = Σ_v E_v · Vol(v ∩ k) / V_v = Σ_v D_v · m_(v∩k),      m_(v∩k) = ρ_v · Vol(v ∩ k),
    m_k = Σ_v m_(v∩k),                                          D_k = E_k / m_k,

with Vol(v ∩ k) from :func:`tetdose.core.overlap.compute_overlap` (exact clipping). m_k is the mass
the voxel world has where tet k is: so a uniform dose stays uniform exactly, and the energy is
conserved, Σ_k E_k = Σ_v E_v · Vol(v ∩ mesh) / V_v (the voxel energy inside the mesh), both to
round-off. A tet in vacuum voxels (ρ_v = 0) has m_k = 0 and reports dose 0.

The tet's own mass in the mesh, m_k^mesh = ¼ Vol Σρ_a (:func:`tetdose.core.mass.tet_mass_g`), is
the voxel one only as far as the CT resolves the tet: for a CT voxelised from this mesh
(:func:`tetdose.core.voxelize.voxelize`) the two agree voxel by voxel, not tet by tet. Where they
differ, D_k is the better dose (partial-volume voxels keep their dose instead of dividing a
lung-and-tissue voxel's energy by lung's mass), and E_k the energy; accumulation over phases on
the mesh (:mod:`tetdose.dose.accumulate`) takes D_k with the mesh masses.

The map is linear in the voxel energies, so it is applied to every batch row of a voxel
:class:`~tetdose.transport.history.result.DoseResult` (:func:`result_onto_mesh`) and the
uncertainty follows from the batches as for tetdose's own tallies.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import scipy.sparse as sp

from tetdose._constants import G_PER_KG, MM3_PER_CM3
from tetdose._typing import FloatArray
from tetdose.core.image import Image, ImageGrid
from tetdose.core.mesh import TetMesh
from tetdose.core.overlap import Overlap, compute_overlap
from tetdose.errors import DensityError, GeometryMismatchError
from tetdose.transport.history.result import DoseResult

#: Largest fraction of a tet's volume that may lie outside the dose grid (round-off of the
#: exact overlap is ~1e-13; a grid that does not cover the mesh is refused, not extrapolated).
COVERAGE_TOL = 1e-9


def mesh_overlap(mesh: TetMesh, grid: ImageGrid, overlap: Overlap | None = None, *,
                 coverage_tol: float = COVERAGE_TOL) -> Overlap:
    """The exact tet ∩ voxel overlap of ``mesh`` with ``grid``, checked to cover every tet.

    Raises :class:`GeometryMismatchError` when a tet lies partly outside the grid (more than
    ``coverage_tol`` of its volume) or a given ``overlap`` belongs to another mesh or grid.
    """
    if overlap is None:
        overlap = compute_overlap(mesh, grid)
    elif overlap.n_tets != mesh.n_tets or not overlap.grid.same_as(grid):
        raise GeometryMismatchError("the overlap was computed for another mesh or grid; "
                                    "pass overlap=None to recompute it")
    volume = mesh.volumes_mm3
    outside = 1.0 - overlap.covered_volume_per_tet_mm3() / volume
    bad = np.flatnonzero(outside > coverage_tol)
    if len(bad):
        lo, hi = mesh.bounds_mm()
        raise GeometryMismatchError(
            f"the dose grid does not cover the mesh: {len(bad)} of {mesh.n_tets} tetrahedra lie "
            f"partly outside it (up to {100 * outside.max():.3g} % of a tet's volume; mesh box "
            f"{np.round(lo, 1).tolist()} … {np.round(hi, 1).tolist()} mm); compute the dose on a "
            "grid that contains the whole mesh (e.g. the CT the mesh was mapped from)")
    return overlap


def voxel_share(mesh: TetMesh, grid: ImageGrid, overlap: Overlap | None = None) -> sp.csr_matrix:
    """Sparse (M, V) matrix S with S_kv = Vol(v ∩ k) / V_v: the share of voxel v's energy that
    lies in tet k (rows: tets in mesh order; columns: flat voxel ids)."""
    ov = mesh_overlap(mesh, grid, overlap)
    return sp.csr_matrix((ov.volume_mm3 / grid.voxel_volume_mm3, ov.voxel, ov.tet_ptr),
                         shape=(mesh.n_tets, grid.n_voxels))


def _density(density: Image, grid: ImageGrid) -> FloatArray:
    grid.require_same(density.grid, "the dose and the density image")
    rho = np.asarray(density.array, dtype=np.float64).ravel()
    if not np.all(rho >= 0.0):
        raise DensityError("the density image has NaN or negative values; give the density "
                           "[g/cm³] the voxel dose was computed with")
    return rho


def voxel_mass_in_tets_g(density: Image, share: sp.csr_matrix) -> FloatArray:
    """m_k = Σ_v ρ_v Vol(v ∩ k) [g]: the voxel world's mass where each tet is."""
    rho = np.asarray(density.array, dtype=np.float64).ravel()
    voxel_mass_g = rho * density.grid.voxel_volume_mm3 / MM3_PER_CM3
    return share @ voxel_mass_g


def voxel_dose_onto_mesh(dose: Image, density: Image, mesh: TetMesh, *,
                         overlap: Overlap | None = None) -> tuple[FloatArray, FloatArray]:
    """(dose per tet [Gy], energy per tet [J]) of a voxel dose [Gy] computed on ``density``
    [g/cm³] (module docstring: E_k = Σ_v D_v ρ_v Vol(v ∩ k), D_k = E_k / m_k).

    ``overlap``: a precomputed :func:`~tetdose.core.overlap.compute_overlap` of this mesh and
    grid (breathing phases on one CT share none, but repeated calls on one phase can). Raises
    :class:`GeometryMismatchError` when the grids differ or the grid does not cover the mesh.
    """
    grid = dose.grid
    rho = _density(density, grid)
    share = voxel_share(mesh, grid, overlap)
    d_v = np.asarray(dose.array, dtype=np.float64).ravel()
    voxel_mass_g = rho * grid.voxel_volume_mm3 / MM3_PER_CM3
    energy_j = share @ (d_v * voxel_mass_g / G_PER_KG)
    mass_kg = share @ voxel_mass_g / G_PER_KG
    dose_gy = np.divide(energy_j, mass_kg, out=np.zeros_like(energy_j), where=mass_kg > 0)
    return dose_gy, energy_j


def result_onto_mesh(result: DoseResult, density: Image, mesh: TetMesh, *,
                     overlap: Overlap | None = None) -> DoseResult:
    """A voxel :class:`DoseResult` as a mesh result: every batch row of voxel energy [MeV] split
    onto the tets (E_k = Σ_v E_v S_kv), masses m_k = Σ_v ρ_v Vol(v ∩ k); the ledger, counters
    and record stay the run's. ``density`` must be the image the voxel run transported in."""
    if result.geometry != "voxel" or result.grid is None:
        raise GeometryMismatchError(f"a {result.geometry} result cannot be put on a mesh by "
                                    "voxel overlaps; give the voxel result of the run")
    _density(density, result.grid)
    share = voxel_share(mesh, result.grid, overlap)
    energy = np.asarray((share @ result.energy_per_batch_mev.T).T)
    return replace(result, energy_per_batch_mev=np.ascontiguousarray(energy),
                   mass_g=voxel_mass_in_tets_g(density, share), geometry="mesh", grid=None,
                   n_tets=mesh.n_tets, on_grid=None, water_ratio=None,
                   extra={**result.extra, "dose_on_mesh": "voxel energy split by exact "
                          "tet-voxel overlaps over the voxel mass in each tet"})
