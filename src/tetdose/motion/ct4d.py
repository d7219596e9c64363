"""4D virtual CT: every breathing phase voxelized on the reference CT's grid (paper §III, Fig. 9).

For phase t, voxel j gets (``tetdose.core.voxelize``, mass-exact partial volumes)

    ρ_j(t) = [m_j(t) + ρ_bg,j(t) · (Vol(V_j) − c_j(t))] / Vol(V_j),

m_j(t) the mesh mass inside the voxel, c_j(t) the covered volume, and the background
ρ_bg(t) outside the mesh:
  * ``"ct"`` (default): the reference CT's density, **not moved** — tissue outside the mesh
    stays where it was, unless a DVF is given for the phase, in which case the reference CT is
    warped by the pull-back I_t(x) = I_0(x + v(x)) (v the inverse DVF, see
    :mod:`tetdose.motion.dvf`) before being used as background;
  * ``"air"``: 0.0012 g/cm³; or a constant density [g/cm³].
CT numbers are HU_j = calibration.hu_of(ρ_j) (the calibration's inverse: the lowest HU with
that density), rounded to integers. Outside the mesh the reference HU therefore come back as
hu_of(density(HU)), identical except in non-monotonic parts of the calibration curve.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from tqdm import tqdm

from tetdose._atomic import atomic_write_dir
from tetdose._constants import AIR_DENSITY_G_CM3
from tetdose.core.calibration import HUCalibration
from tetdose.core.image import Image
from tetdose.core.io import write_image
from tetdose.core.voxelize import voxelize
from tetdose.errors import ImageError, MeshError, TetdoseError
from tetdose.motion.dvf import DisplacementField, warp_image
from tetdose.motion.phases import PhaseSeries

#: Lowest and highest CT number written [HU] (int16 storage).
HU_MIN, HU_MAX = -1024, 3071
FORMATS = ("dicom", "nrrd")


def virtual_4dct(series: PhaseSeries, ct_hu: Image, *, calibration: HUCalibration | None = None,
                 background: str | float = "ct",
                 dvfs: Sequence[DisplacementField] | None = None, partial: str = "mass",
                 progress: bool = False) -> list[Image]:
    """One HU image per phase of ``series`` (which must carry densities) on ``ct_hu``'s grid."""
    cal = calibration or HUCalibration.schneider2000()
    densities = phase_densities(series, ct_hu, calibration=cal, background=background, dvfs=dvfs,
                                partial=partial, progress=progress)
    return [to_hu(rho, cal) for rho in densities]


def phase_densities(series: PhaseSeries, ct_hu: Image, *,
                    calibration: HUCalibration | None = None, background: str | float = "ct",
                    dvfs: Sequence[DisplacementField] | None = None, partial: str = "mass",
                    progress: bool = False) -> list[Image]:
    """The density [g/cm³] behind :func:`virtual_4dct`: each phase voxelized on ``ct_hu``'s grid."""
    if series.density_g_cm3 is None:
        raise MeshError("the phases carry no density; run `tetdose deform` (or "
                        "conserve.update_series) first")
    if dvfs is not None and len(dvfs) != series.n_phases:
        raise TetdoseError(f"{len(dvfs)} DVFs for {series.n_phases} phases; give one per phase")
    cal = calibration or HUCalibration.schneider2000()
    ct_density = Image(cal.density_checked(ct_hu.array)[0], ct_hu.grid)
    images = []
    for k in tqdm(range(series.n_phases), desc="4D-CT phases", disable=not progress):
        bg = _background(background, ct_density, None if dvfs is None else dvfs[k])
        images.append(voxelize(series.mesh(k), series.density_g_cm3[k], ct_hu.grid,
                               background=bg, partial=partial))
    return images


def to_hu(density: Image, calibration: HUCalibration) -> Image:
    """Density image [g/cm³] → int16 HU through the calibration's inverse, clipped to range."""
    hu = np.clip(np.rint(calibration.hu_of(density.array)), HU_MIN, HU_MAX).astype(np.int16)
    return Image(hu, density.grid)


def _background(background: str | float, ct_density: Image,
                dvf: DisplacementField | None) -> Image | float:
    if isinstance(background, str):
        if background == "air":
            return AIR_DENSITY_G_CM3
        if background != "ct":
            raise TetdoseError(f"background must be 'ct', 'air' or a density, got {background!r}")
        if dvf is None:
            return ct_density
        return warp_image(ct_density, dvf, outside_value=AIR_DENSITY_G_CM3)
    value = float(background)
    if not np.isfinite(value) or value < 0:
        raise TetdoseError(f"background density must be ≥ 0 g/cm³, got {background!r}")
    return value


def write_4dct(images_hu: Sequence[Image], out_dir: str | os.PathLike[str], *,
               phase_percent: Sequence[float], fmt: str = "dicom",
               reference: str | os.PathLike[str] | None = None) -> list[Path]:
    """Write the phases: DICOM (one series folder per phase) or NRRD (one file per phase).

    ``reference``: a DICOM CT folder whose patient/study the series join (DICOM only). The
    whole ``out_dir`` is written atomically either way.
    """
    if fmt not in FORMATS:
        raise ImageError(f"unknown 4D-CT format {fmt!r}; use one of {FORMATS}")
    if fmt == "dicom":
        from tetdose.dicom import write_ct_series_4d

        ref = reference if reference is not None and Path(reference).is_dir() else None
        return write_ct_series_4d(list(images_hu), out_dir, phase_percent=phase_percent,
                                  reference=ref)
    out = Path(out_dir)
    names = [f"phase_{p:05.1f}.nrrd" for p in phase_percent]
    if len(set(names)) != len(names):
        raise ImageError(f"phase percentages {list(phase_percent)} are not distinct")
    with atomic_write_dir(out) as tmp:
        for name, image in zip(names, images_hu, strict=True):
            write_image(tmp / name, image)
    return [out / n for n in names]
