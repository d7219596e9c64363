"""Exceptions raised by tetdose. Every message says what is wrong and how to fix it."""


class TetdoseError(Exception):
    """Base class of every error tetdose raises on bad input."""


class MeshError(TetdoseError):
    """A tetrahedral mesh is unusable (inverted or degenerate cells, NaN points, no tetrahedra)."""


class ImageError(TetdoseError):
    """An image is unusable (non-uniform slices, wrong modality, unreadable file)."""


class GeometryMismatchError(TetdoseError):
    """Two objects do not share the space they must (mesh outside the CT, grids differ)."""


class TopologyMismatchError(TetdoseError):
    """Phase meshes do not share the reference mesh's cells."""


class CalibrationError(TetdoseError):
    """An HU → density calibration is not a valid piecewise-linear curve."""


class DicomError(TetdoseError):
    """A DICOM dataset cannot be written or read as asked."""


class PlanError(TetdoseError):
    """A treatment plan (beams, materials, normalization) is invalid."""
