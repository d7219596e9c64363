"""tetdose: CT density on deformable tetrahedral meshes, 4D virtual CT and photon dose."""
# ruff: noqa: I001  (the version is imported first: submodules read it during import)

from tetdose._version import __version__

from tetdose import _moved

from tetdose import phantoms
from tetdose.core.calibration import HUCalibration
from tetdose.dicom import write_ct_series, write_ct_series_4d, write_rt_dose
from tetdose.errors import (
    CalibrationError,
    GeometryMismatchError,
    ImageError,
    MeshError,
    TetdoseError,
    TopologyMismatchError,
)
from tetdose.core.image import Image, ImageGrid
from tetdose.core.io import read_ct, read_image, read_mesh, write_image, write_mesh
from tetdose.mapping import DensityMap, map_density
from tetdose.mapping.metrics import evaluate
from tetdose.core.mesh import TetMesh
from tetdose.motion import BreathingModel, PhaseSeries, update_series
from tetdose.motion.ct4d_read import Phase4D, read_4dct
from tetdose.study import StudyConfig, run_study
from tetdose.transport import (
    DoseResult,
    PhotonSource,
    Plan,
    TransportSettings,
    run_mesh_transport,
    run_voxel_transport,
    simulate,
)
from tetdose.transport.geometry.world import World
from tetdose.core.voxelize import voxelize

__all__ = [
    "BreathingModel",
    "CalibrationError",
    "DensityMap",
    "DoseResult",
    "GeometryMismatchError",
    "HUCalibration",
    "Image",
    "ImageError",
    "ImageGrid",
    "MeshError",
    "Phase4D",
    "PhaseSeries",
    "PhotonSource",
    "Plan",
    "StudyConfig",
    "TetMesh",
    "TetdoseError",
    "TopologyMismatchError",
    "TransportSettings",
    "__version__",
    "evaluate",
    "map_density",
    "phantoms",
    "read_4dct",
    "read_ct",
    "read_image",
    "read_mesh",
    "run_mesh_transport",
    "run_study",
    "run_voxel_transport",
    "simulate",
    "World",
    "update_series",
    "voxelize",
    "write_ct_series",
    "write_ct_series_4d",
    "write_image",
    "write_mesh",
    "write_rt_dose",
]

_moved.install()  # old module paths import for one more release, with a DeprecationWarning
