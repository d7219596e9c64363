"""Mapping error metrics of the paper's §IV.B, over a region of interest of the CT.

- Mass(image) = Σ_j ρ(V_j) Vol(V_j) over the ROI voxels (eq. 21);
- Mass(mesh) = Σ_k m(T_k) (eq. 22, m from eq. 3);
- Error(mass) = |Mass(image) − Mass(mesh)| / Mass(image) · 100 (eq. 23);
- e_j = |ρ(V_j) − ρ(Ṽ_j)| / ρ(V_j) · 100, RMDE = mean e_j (eq. 24–25), ESD = std e_j (eq. 26),
  with Ĩ the image reconstructed from the mesh (§III); also the median of e_j, since a few
  near-air voxels (ρ ≈ 0.001 g/cm³) can dominate the mean in lung.

Eq. 23 compares voxel mass with mesh mass, so on a mesh that does not follow voxel faces it also
counts the voxels cut by the organ surface. We therefore also report the mapping's own mass
error, against the CT mass *inside the mesh* (Σ_kj Vol(V_j ∩ T_k) ρ(V_j)).

With a given ROI (a structure, ``--mask``) eq. 23 would compare the whole mesh's mass with the
CT mass of part of it (a 2.5 cm tumour against a mesh of both lungs: "8232 %"), so there
Error(mass) compares like with like: the CT mass of the ROI voxels with the reconstruction's
mass in the same voxels, |Σ_ROI ρ − Σ_ROI ρ̃| / Σ_ROI ρ.

The reconstruction Ĩ uses plain partial volume with the original CT outside the mesh, so a voxel
cut by the surface compares like with like. The default ROI is the voxels at least half covered
by the mesh; a label image can be given instead.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from tetdose._constants import MM3_PER_CM3
from tetdose._typing import BoolArray
from tetdose.core.calibration import HUCalibration
from tetdose.core.image import Image, check_ct_hu
from tetdose.core.mass import tet_mass_g
from tetdose.core.mesh import TetMesh
from tetdose.core.overlap import Overlap, compute_overlap
from tetdose.core.voxelize import voxelize
from tetdose.errors import GeometryMismatchError, ImageError

#: Default ROI: voxels whose covered fraction is at least this.
ROI_MIN_COVER = 0.5


@dataclass(frozen=True)
class MappingMetrics:
    """Numbers of §IV.B (masses in g, errors in %)."""

    n_voxels: int
    image_mass_g: float  # eq. 21 over the ROI
    mesh_mass_g: float  # eq. 22
    mass_error_pct: float  # eq. 23 (a given ROI: against the reconstruction's mass in it)
    ct_mass_in_mesh_g: float
    mass_error_in_mesh_pct: float
    rmde_pct: float  # eq. 24–25
    esd_pct: float  # eq. 26
    median_error_pct: float  # median of e_j: robust where near-air voxels make e_j explode
    mean_abs_error_g_cm3: float

    def as_dict(self) -> dict[str, float]:
        return asdict(self)


@dataclass(frozen=True, eq=False)
class Evaluation:
    """Metrics plus the images behind them (densities in g/cm³, relative error in %)."""

    metrics: MappingMetrics
    original: Image
    reconstruction: Image
    abs_error: Image
    relative_error_pct: Image
    roi: Image


def evaluate(ct_hu: Image, mesh: TetMesh, density_g_cm3: np.ndarray, *,
             calibration: HUCalibration | None = None, roi: BoolArray | None = None,
             overlap: Overlap | None = None) -> Evaluation:
    """Compare the CT with its reconstruction from the mesh density (see module docstring).

    ``roi`` is a boolean array of the CT's shape; default: voxels ≥ 50 % inside the mesh.
    """
    check_ct_hu(ct_hu)
    calibration = calibration or HUCalibration.schneider2000()
    grid = ct_hu.grid
    ov = overlap if overlap is not None else compute_overlap(mesh, grid)
    original = ct_hu.with_array(calibration.density_checked(ct_hu.array)[0])
    recon = voxelize(mesh, density_g_cm3, grid, background=original, partial="mass", overlap=ov)
    cover = ov.covered_volume_per_voxel_mm3().reshape(grid.shape) / grid.voxel_volume_mm3
    mask = (cover >= ROI_MIN_COVER) if roi is None else np.asarray(roi, dtype=bool)
    if mask.shape != grid.shape:
        raise GeometryMismatchError(f"roi shape {mask.shape} differs from the CT's "
                                    f"{grid.shape}; give a mask on the CT grid")
    if not mask.any():
        raise ImageError("the region of interest holds no voxel; give a mask that overlaps "
                         "the mesh")
    rho, rec = original.array[mask], recon.array[mask]
    err = np.abs(rho - rec)
    rel = 100.0 * err / rho
    v_cm3 = grid.voxel_volume_mm3 / MM3_PER_CM3
    image_mass = float(rho.sum() * v_cm3)
    mesh_mass = float(tet_mass_g(mesh, density_g_cm3).sum())
    compared = mesh_mass if roi is None else float(rec.sum() * v_cm3)  # like with like
    in_mesh = float(np.dot(ov.volume_mm3, original.array.ravel()[ov.voxel]) / MM3_PER_CM3)
    metrics = MappingMetrics(
        n_voxels=int(mask.sum()),
        image_mass_g=image_mass,
        mesh_mass_g=mesh_mass,
        mass_error_pct=100.0 * abs(image_mass - compared) / image_mass,
        ct_mass_in_mesh_g=in_mesh,
        mass_error_in_mesh_pct=100.0 * abs(in_mesh - mesh_mass) / in_mesh,
        rmde_pct=float(rel.mean()),
        esd_pct=float(rel.std()),
        median_error_pct=float(np.median(rel)),
        mean_abs_error_g_cm3=float(err.mean()),
    )
    abs_err = np.where(mask, np.abs(original.array - recon.array), 0.0)
    rel_img = np.where(mask, 100.0 * abs_err / np.where(mask, original.array, 1.0), 0.0)
    return Evaluation(metrics, original, recon, ct_hu.with_array(abs_err),
                      ct_hu.with_array(rel_img), ct_hu.with_array(mask.astype(np.uint8)))
