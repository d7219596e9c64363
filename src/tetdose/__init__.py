"""tetdose: CT density on deformable tetrahedral meshes, 4D virtual CT and photon dose."""
# ruff: noqa: I001  (the version is imported first: submodules read it during import)

from tetdose._version import __version__  # first: submodules import it

from tetdose import phantoms
from tetdose.calibration import HUCalibration
from tetdose.dicom import write_ct_series, write_ct_series_4d, write_rt_dose
from tetdose.errors import (
    CalibrationError,
    GeometryMismatchError,
    ImageError,
    MeshError,
    TetdoseError,
    TopologyMismatchError,
)
from tetdose.image import Image, ImageGrid
from tetdose.io import read_ct, read_image, read_mesh, write_image, write_mesh
from tetdose.mapping import DensityMap, map_density
from tetdose.mapping.metrics import evaluate
from tetdose.mesh import TetMesh
from tetdose.voxelize import voxelize

__all__ = [
    "CalibrationError",
    "DensityMap",
    "GeometryMismatchError",
    "HUCalibration",
    "Image",
    "ImageError",
    "ImageGrid",
    "MeshError",
    "TetMesh",
    "TetdoseError",
    "TopologyMismatchError",
    "__version__",
    "evaluate",
    "map_density",
    "phantoms",
    "read_ct",
    "read_image",
    "read_mesh",
    "voxelize",
    "write_ct_series",
    "write_ct_series_4d",
    "write_image",
    "write_mesh",
    "write_rt_dose",
]
