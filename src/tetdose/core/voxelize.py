"""Virtual CT: mesh density back onto a voxel grid, exact and mass preserving (paper §III).

Voxel mass (eq. 14–15): m(V_j) = Σ_k ∫_{V_j ∩ T_k} ρ dV = Σ_k Σ_a ρ_a ∫_{V_j ∩ T_k} λ_a dV, exact
for a density linear in each tetrahedron (barycentric moments from :mod:`tetdose.core.overlap`).

Voxels only partly inside the mesh (covered volume c_j < Vol(V_j)):

- ``partial="mass"`` (plain partial volume): ρ_j = (m_j + ρ_bg,j (Vol(V_j) − c_j)) / Vol(V_j);
  Σ_j m_j equals the mesh mass exactly (for a mesh inside the grid);
- ``partial="extrapolate"`` (the paper's option): ρ_j = m_j / c_j, the inside density spread
  over the whole voxel.

Voxels the mesh does not touch get the background: ``"air"`` (0.0012 g/cm³), a constant
[g/cm³], or an :class:`Image` of densities on the same grid (e.g. the original CT).
"""

from __future__ import annotations

import numpy as np

from tetdose._checks import check_density
from tetdose._constants import AIR_DENSITY_G_CM3, MM3_PER_CM3
from tetdose._typing import FloatArray
from tetdose.core.image import Image, ImageGrid
from tetdose.core.mass import pair_mass_g
from tetdose.core.mesh import TetMesh
from tetdose.core.overlap import Overlap, compute_overlap
from tetdose.errors import MeshError, OptionError

PARTIAL_MODES = ("mass", "extrapolate")
#: Voxels covered by less than this fraction count as untouched in "extrapolate" mode.
MIN_COVER_FRACTION = 1e-9


def voxelize(mesh: TetMesh, density_g_cm3: FloatArray, grid: ImageGrid, *,
             background: str | float | Image = "air", partial: str = "mass",
             overlap: Overlap | None = None, progress: bool = False) -> Image:
    """Density image [g/cm³] of the mesh's linear density on ``grid`` (see module docstring).

    ``overlap`` may pass a precomputed intersection of this mesh with this grid. NaN or
    infinite densities (or background) are refused (:func:`tetdose._checks.check_density`);
    negative ones are warned about where they arise (``map_density``) and refused where a
    mesh is read by the command line.
    """
    if partial not in PARTIAL_MODES:
        raise OptionError(f"partial must be one of {PARTIAL_MODES}, got {partial!r}")
    density = np.asarray(density_g_cm3, dtype=np.float64)
    if density.shape != (mesh.n_points,):
        raise MeshError(f"density must have one value per point ({mesh.n_points}), "
                        f"got shape {density.shape}")
    check_density(density, what="vertex densities", fix="map the mesh again or fix its "
                  "point_data 'density'", negative="allow")
    ov = overlap if overlap is not None else compute_overlap(mesh, grid, progress=progress)
    # Work on the voxels the mesh touches only: memory ∝ pairs plus the one output array.
    touched, pair_to_touched = np.unique(ov.voxel, return_inverse=True)
    pair_mass = pair_mass_g(mesh, ov, density)
    mass_g = np.bincount(pair_to_touched, weights=pair_mass, minlength=len(touched))
    covered = np.bincount(pair_to_touched, weights=ov.volume_mm3, minlength=len(touched))
    bg = _background(background, grid)
    rho = np.array(bg, dtype=np.float64) if np.ndim(bg) else np.full(grid.n_voxels, float(bg))
    bg_touched = rho[touched]
    v = grid.voxel_volume_mm3
    if partial == "mass":
        rho[touched] = (mass_g * MM3_PER_CM3 + bg_touched * np.clip(v - covered, 0.0, None)) / v
    else:
        hit = covered > MIN_COVER_FRACTION * v
        rho[touched[hit]] = mass_g[hit] * MM3_PER_CM3 / covered[hit]
    return Image(rho.reshape(grid.shape), grid)


def _background(background: str | float | Image, grid: ImageGrid) -> FloatArray | float:
    if isinstance(background, Image):
        grid.require_same(background.grid, "the background image and the target grid")
        return check_density(background.array, what="background voxel densities",
                             fix="check the CT and its calibration").ravel()
    if isinstance(background, str):
        if background != "air":
            raise OptionError(f"background must be 'air', a density [g/cm³] or an Image, got "
                              f"{background!r}")
        return AIR_DENSITY_G_CM3
    value = float(background)
    if not np.isfinite(value) or value < 0:
        raise OptionError(f"the background density must be a finite number ≥ 0 g/cm³, got "
                          f"{background!r}")
    return value
