"""Exceptions raised by tetdose. Every message says what is wrong and how to fix it.

The taxonomy (one class per kind of fault, so callers catch what they can fix):

- :class:`MeshError`, :class:`ImageError`, :class:`CalibrationError`, :class:`DicomError`,
  :class:`PlanError`: an input of that kind is unusable;
- :class:`GeometryMismatchError`, :class:`TopologyMismatchError`: two inputs do not fit together;
- :class:`DensityError`: densities are NaN, infinite or negative;
- :class:`OptionError`: a parameter (CLI option or keyword argument) is out of range or unknown;
- :class:`OutputError`: an output path is refused (it is an input, a foreign folder, a file
  where a folder is needed, unwritable, or has an unknown extension);
- :class:`DoseError`: a dose distribution cannot be used as asked (e.g. zero everywhere);
- :class:`SolverError`: a numerical method failed to converge.

``OptionError``, ``DensityError`` and ``DoseError`` are also ``ValueError`` and ``SolverError``
a ``RuntimeError``, so code that caught the built-in types before keeps working.
The command line prints every :class:`TetdoseError` as one line and exits with code 2.
"""


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


class DensityError(TetdoseError, ValueError):
    """Densities [g/cm³] are NaN, infinite or negative."""


class OptionError(TetdoseError, ValueError):
    """A parameter (command-line option or keyword argument) is out of range or unknown."""


class OutputError(TetdoseError):
    """An output path is refused: it is an input, a folder tetdose did not write, unwritable…"""


class DoseError(TetdoseError, ValueError):
    """A dose distribution cannot be used as asked (zero everywhere, nothing above threshold)."""


class SolverError(TetdoseError, RuntimeError):
    """A numerical method (linear solver, iteration) did not converge."""
