"""Dose comparison: gamma index, DVHs, profiles, reports, and the mesh-vs-voxel workflow.

Mesh ↔ grid transfer and point location, which comparison, accumulation and the 4D dose all
build on, live in :mod:`tetdose.core.transfer`; accumulation over breathing phases in
:mod:`tetdose.dose.accumulate`.
"""

from tetdose.compare.dvh import DVH, dvh, image_dvh, mesh_dvh
from tetdose.compare.gamma import GammaResult, gamma_index
from tetdose.compare.profiles import Profile, image_profile, mesh_profile

__all__ = ["DVH", "GammaResult", "Profile", "dvh", "gamma_index", "image_dvh", "image_profile",
           "mesh_dvh", "mesh_profile"]
