"""The transport world: a tetrahedral mesh, a density image, or a mesh inside an image (hybrid).

A physicist meshes what moves (lungs, tumour, liver) and keeps the rest of the patient as CT
voxels. ``World(mesh=mapped, density=ct_density)`` is that patient: inside the mesh the mesh is
the only truth (linear vertex density, region materials); outside it, the voxels (density per
voxel, density-class or label materials). ``World(mesh=...)`` alone is a mesh in vacuum (photons
that leave it re-enter wherever their path meets it again); ``World(density=...)`` alone is the
voxel phantom. One history moves between the parts any number of times with exact geometry
(:mod:`tetdose.transport.geometry._world`).

Masses for dose: a tet's mass is Vol·mean of its vertex densities (exact for the linear
density); a voxel's mass is its density times the part of its volume the mesh does not cover,
``m_j = ρ_j·(Vol(V_j) − Σ_k Vol(T_k ∩ V_j))`` (exact tet ∩ voxel overlaps,
:mod:`tetdose.core.overlap`), so a voxel wholly inside the mesh has no voxel mass and no voxel
dose. The same overlaps put the mesh's energy on the grid for the combined dose image
(:meth:`tetdose.transport.history.result.DoseResult.combined`).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from tetdose._typing import FloatArray, IntArray
from tetdose.core.image import Image, ImageGrid
from tetdose.core.mass import mass_g, pair_mass_g
from tetdose.core.mesh import TetMesh
from tetdose.errors import ImageError, MeshError, PlanError
from tetdose.transport.geometry._tet import TetGeometry
from tetdose.transport.geometry._voxel import VoxelGeometry
from tetdose.transport.geometry._world import LIST_PAD_MM, WorldGeometry, list_triangles_per_voxel
from tetdose.transport.geometry.tets import (
    empty_mesh_geometry,
    material_density_max,
    mesh_geometry,
    morton_order,
)

#: (mean density per cell [g/cm³], region label per cell or None) → (material index per cell,
#: material names).
MaterialRule = Callable[[FloatArray, "IntArray | None"], tuple[IntArray, list[str]]]
#: A voxel whose uncovered volume is below this fraction is wholly inside the mesh (round-off of
#: the summed overlap volumes): no voxel mass, no voxel dose.
COVERED_TOL_REL = 1e-9
#: Share of the mesh's mass outside the CT grid above which a hybrid run warns.
OUTSIDE_WARN_FRACTION = 0.01


@dataclass(frozen=True, eq=False)
class World:
    """Where photons travel: ``mesh`` (point_data ``density`` [g/cm³], optional ``region``),
    ``density`` (an :class:`Image` of g/cm³, e.g. the CT through :class:`HUCalibration`) and its
    optional ``labels`` image (region → material through the plan's ``[materials]``).

    At least one of ``mesh`` and ``density`` is needed. With both, a mesh reaching beyond the
    image's grid meets vacuum there (a warning above 1 % of its mass).
    """

    mesh: TetMesh | None = None
    density: Image | None = None
    labels: Image | None = None

    def __post_init__(self) -> None:
        if self.mesh is None and self.density is None:
            raise PlanError("a transport world needs a mesh, a density image, or both")
        if self.mesh is not None and not isinstance(self.mesh, TetMesh):
            raise PlanError(f"World.mesh must be a TetMesh, got {type(self.mesh).__name__}")
        if self.density is not None and not isinstance(self.density, Image):
            raise PlanError(f"World.density must be an Image, got {type(self.density).__name__}")
        if self.labels is not None:
            if self.density is None:
                raise PlanError("a label image needs the density image it labels")
            self.density.grid.require_same(self.labels.grid, "density and label images")

    @property
    def kind(self) -> str:
        """``"mesh"``, ``"voxel"`` or ``"hybrid"``."""
        if self.mesh is None:
            return "voxel"
        return "mesh" if self.density is None else "hybrid"

    @property
    def grid(self) -> ImageGrid | None:
        return None if self.density is None else self.density.grid


def as_world(geometry: TetMesh | Image | World, labels: Image | None = None) -> World:
    """``geometry`` as a :class:`World`: a mesh alone, a density image (with ``labels``) alone,
    or the world itself."""
    if isinstance(geometry, World):
        if labels is not None:
            raise PlanError("give the label image inside the World (World(labels=...))")
        return geometry
    if isinstance(geometry, TetMesh):
        return World(mesh=geometry)
    if isinstance(geometry, Image):
        return World(density=geometry, labels=labels)
    raise PlanError(f"geometry must be a World, a TetMesh or an Image of densities, got "
                    f"{type(geometry).__name__}")


@dataclass(frozen=True, eq=False)
class MeshOnGrid:
    """Where the mesh's matter lies on the grid: overlap pairs (tet k, voxel j) with the mass
    m_kj [g] of tet k inside voxel j (exact for the linear density)."""

    tet: IntArray
    voxel: IntArray
    mass_g: FloatArray


@dataclass(frozen=True, eq=False)
class WorldArrays:
    """A world flattened for the kernels: geometry, per-cell material and mass (mesh order)."""

    geometry: WorldGeometry
    material_names: list[str]
    material_of_cell: IntArray  # (M + V,) material index per cell, mesh order then voxels
    mass_g: FloatArray  # (M + V,)
    order: IntArray | None  # kernel tet i is mesh tet order[i]
    on_grid: MeshOnGrid | None


def mesh_density(mesh: TetMesh) -> FloatArray:
    """Vertex densities [g/cm³] of a mapped mesh, checked finite and ≥ 0."""
    if "density" not in mesh.point_data:
        raise MeshError("the mesh has no point_data 'density' (g/cm³); map a CT onto it first "
                        "(tetdose map)")
    rho = np.asarray(mesh.point_data["density"], dtype=np.float64).reshape(-1)
    if rho.shape != (mesh.n_points,) or not np.all(np.isfinite(rho)) or np.any(rho < 0):
        raise MeshError(f"vertex densities must be {mesh.n_points} finite values ≥ 0 g/cm³")
    return rho


def voxel_density(density: Image) -> FloatArray:
    """Flat voxel densities [g/cm³], checked finite and ≥ 0."""
    rho = np.ascontiguousarray(density.array, dtype=np.float64).reshape(-1)
    if not np.all(np.isfinite(rho)) or np.any(rho < 0):
        raise ImageError("the density image must hold finite values ≥ 0 g/cm³; convert HU to "
                         "density first (HUCalibration)")
    return rho


def _voxel_geometry(grid: ImageGrid | None, rho: FloatArray, material: IntArray) -> VoxelGeometry:
    if grid is None:
        return VoxelGeometry(np.zeros(3), np.ones(3), np.zeros(3, np.intp), np.zeros(0),
                             np.zeros(0, np.intp))
    spacing = grid.spacing_mm
    return VoxelGeometry(-0.5 * spacing, spacing.copy(), np.array(grid.size, dtype=np.intp),
                         rho, np.array(material, dtype=np.intp))  # a copy: flagged in place


def _flag_listed_voxels(material: IntArray, tri_lo: IntArray, tri_n: IntArray,
                        start: IntArray, items: IntArray, n: IntArray) -> None:
    """Mark, in place, the voxels that list mesh triangles: material m → −m − 1 (see
    :class:`~tetdose.transport.geometry._voxel.VoxelGeometry`), so the voxel flight tests
    triangles only there, without a second per-step load."""
    listed = np.flatnonzero(np.diff(start) > 0)
    li = listed % tri_n[0]
    lj = (listed // tri_n[0]) % tri_n[1]
    lk = listed // (tri_n[0] * tri_n[1])
    vid = ((lk + tri_lo[2]) * n[1] + lj + tri_lo[1]) * n[0] + li + tri_lo[0]
    material[vid] = -material[vid] - 1


def _with_box_voxels(tet: TetGeometry, vox: VoxelGeometry, material: IntArray,
                     n_materials: int) -> TetGeometry:
    """``tet`` with ``rho_max`` [g/cm³] per material over the mesh's vertices and the voxels
    (material ``material``, unflagged) meeting the point-location box: there, outside the mesh,
    the photon's Woodcock flight sees the voxels (:mod:`tetdose.transport.history._delta`)."""
    box_lo = tet.loc_lo
    box_hi = tet.loc_lo + tet.loc_n * tet.loc_cell
    i0 = np.clip(np.floor((box_lo - vox.lo) / vox.cell).astype(np.intp), 0, vox.n - 1)
    i1 = np.clip(np.floor((box_hi - vox.lo) / vox.cell).astype(np.intp), 0, vox.n - 1)
    inside = (slice(i0[2], i1[2] + 1), slice(i0[1], i1[1] + 1), slice(i0[0], i1[0] + 1))
    shape = tuple(vox.n[::-1])
    rho = np.zeros(n_materials)
    rho[:len(tet.rho_max)] = tet.rho_max
    rho = np.maximum(rho, material_density_max(material.reshape(shape)[inside].ravel(),
                                               vox.density.reshape(shape)[inside].ravel(),
                                               n_materials))
    return tet._replace(rho_max=rho)


def _warn_if_outside(mesh: TetMesh, on_grid: MeshOnGrid, tet_mass_g: FloatArray) -> None:
    """Warn when more than :data:`OUTSIDE_WARN_FRACTION` of the mesh's mass lies outside the CT
    (there the mesh is surrounded by vacuum, not tissue)."""
    outside = 1.0 - on_grid.mass_g.sum() / max(float(tet_mass_g.sum()), 1e-300)
    if outside > OUTSIDE_WARN_FRACTION:
        warnings.warn(f"{100 * outside:.1f} % of the mesh's mass lies outside the CT grid, "
                      "where the mesh is surrounded by vacuum; use a CT that covers the whole "
                      "mesh", stacklevel=4)


def _on_grid(mesh: TetMesh, grid: ImageGrid, rho: FloatArray) -> tuple[MeshOnGrid, FloatArray]:
    """Overlap pairs with their masses, and the covered volume of each voxel [mm³]."""
    from tetdose.core.overlap import compute_overlap

    ov = compute_overlap(mesh, grid)
    m_kj = pair_mass_g(mesh, ov, rho)
    return (MeshOnGrid(ov.tet.astype(np.intp), ov.voxel.astype(np.intp), m_kj),
            ov.covered_volume_per_voxel_mm3())


def world_arrays(world: World, material_of: MaterialRule) -> WorldArrays:
    """Flatten ``world``; ``material_of(mean_density, region)`` gives each cell's material."""
    mesh, grid = world.mesh, world.grid
    empty_i = np.zeros(0, np.intp)
    rho_p = mesh_density(mesh) if mesh is not None else np.zeros(0)
    tet_rho = rho_p[mesh.tets].mean(axis=1) if mesh is not None else np.zeros(0)
    rho_v = voxel_density(world.density) if world.density is not None else np.zeros(0)
    region_v = (None if world.labels is None
                else np.asarray(world.labels.array).reshape(-1).astype(np.int64))
    material, names = material_of(np.concatenate([tet_rho, rho_v]),
                           _regions([tet_rho, rho_v],
                                    [None if mesh is None else mesh.region, region_v]))
    m_tets = len(tet_rho)
    tet, order, on_grid = empty_mesh_geometry(), None, None
    if mesh is not None:
        frame = None
        if grid is not None:
            frame = grid.to_grid_frame
        order = morton_order(mesh.centroids_mm)
        tet = mesh_geometry(mesh, rho_p, material[:m_tets], order, frame)
    vox = _voxel_geometry(grid, rho_v, material[m_tets:])
    lists = (np.zeros(3, np.intp), np.zeros(3, np.intp), np.zeros(1, np.intp), empty_i)
    vox_mass = np.zeros(0)
    if grid is not None:
        covered = np.zeros(grid.n_voxels)
        if mesh is not None:
            on_grid, covered = _on_grid(mesh, grid, rho_p)
            lists = list_triangles_per_voxel(tet.bnd_tri, vox.lo, vox.cell, vox.n, LIST_PAD_MM)
            tet = _with_box_voxels(tet, vox, material[m_tets:], len(names))
            _flag_listed_voxels(vox.material, *lists, vox.n)
        uncovered = grid.voxel_volume_mm3 - covered
        uncovered[uncovered < COVERED_TOL_REL * grid.voxel_volume_mm3] = 0.0  # round-off
        vox_mass = mass_g(uncovered, rho_v)
    tet_mass = mass_g(mesh.volumes_mm3, tet_rho) if mesh is not None else np.zeros(0)
    if on_grid is not None:
        _warn_if_outside(mesh, on_grid, tet_mass)
    return WorldArrays(WorldGeometry(tet, vox, *lists), names, material,
                       np.concatenate([tet_mass, vox_mass]), order, on_grid)


def _regions(rhos: list[FloatArray], regions: list[IntArray | None]) -> IntArray | None:
    """Concatenated region labels (cells of a part without labels get a label no plan uses)."""
    if all(r is None for r in regions):
        return None
    none = np.iinfo(np.int64).min
    return np.concatenate([np.full(len(rho), none, np.int64) if r is None
                           else np.asarray(r, np.int64) for rho, r in zip(rhos, regions,
                                                                           strict=True)])


def voxel_world(vox: VoxelGeometry) -> WorldGeometry:
    """A voxel-only :class:`WorldGeometry` around kernel voxel arrays (no mesh, no lists)."""
    z3 = np.zeros(3, np.intp)
    return WorldGeometry(empty_mesh_geometry(), vox, z3, z3.copy(), np.zeros(1, np.intp),
                         np.zeros(0, np.intp))
