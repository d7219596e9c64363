"""Dose comparison: mesh ↔ voxel resampling, gamma index, DVHs, profiles and reports.

Accumulation over breathing phases lives in :mod:`tetdose.accumulate`.
"""

from tetdose.compare.dvh import DVH, dvh, image_dvh, mesh_dvh
from tetdose.compare.gamma import GammaResult, gamma_index
from tetdose.compare.profiles import Profile, image_profile, mesh_profile
from tetdose.compare.resample import (
    grid_dose_to_mesh,
    locate_points,
    mesh_dose_to_grid,
    mesh_mass_on_grid,
)

__all__ = ["DVH", "GammaResult", "Profile", "dvh", "gamma_index", "grid_dose_to_mesh",
           "image_dvh", "image_profile", "locate_points", "mesh_dose_to_grid", "mesh_dvh",
           "mesh_mass_on_grid", "mesh_profile"]
