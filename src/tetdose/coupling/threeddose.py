"""EGSnrc ``.3ddose`` files (DOSXYZnrc, egs_chamber's 3ddose output, …) ↔ tetdose images.

Layout (DOSXYZnrc Users Manual, NRCC Report PIRS-794, "the .3ddose file"): whitespace-separated
numbers in six blocks, each block may span any number of lines:

1. nx ny nz — the number of voxels along x, y, z;
2. the nx + 1 voxel boundaries along x [cm], then 3. the ny + 1 along y, 4. the nz + 1 along z;
5. the nx·ny·nz doses, x fastest, then y, then z [Gy per incident particle, or per the
   normalisation of the run];
6. the nx·ny·nz relative statistical uncertainties (fractions of the dose, same order).

EGSnrc phantoms built by ``ctcreate`` from a CT keep the CT's patient axes (x, y, z of DICOM
LPS, in cm), so the grid maps onto a tetdose :class:`~tetdose.core.image.ImageGrid` with the
identity direction, spacing = boundary step × 10 mm and origin = first voxel centre × 10 mm.
"x fastest" is the C order of tetdose's ``(nz, ny, nx)`` arrays, so the dose block reshapes
directly. tetdose grids are uniform: boundaries whose steps differ by more than
:data:`UNIFORM_RTOL` of the step are refused (DOSXYZnrc allows non-uniform voxels).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from tetdose._atomic import atomic_write_file
from tetdose._constants import MM_PER_CM
from tetdose.core.image import Image, ImageGrid
from tetdose.errors import ImageError

#: Largest relative spread of the voxel steps along an axis accepted as a uniform grid (the
#: boundaries are printed with ~4–6 decimals of a cm).
UNIFORM_RTOL = 1e-4


def read_3ddose(path: str | os.PathLike[str]) -> tuple[Image, Image]:
    """(dose [as in the file], relative uncertainty) images of a ``.3ddose`` file."""
    path = Path(path)
    if not path.is_file():
        raise ImageError(f"{path} does not exist; give a .3ddose file")
    try:
        values = np.array(path.read_text(errors="replace").split(), dtype=np.float64)
    except ValueError as exc:
        raise ImageError(f"{path} is not a .3ddose file (a non-number: {exc})") from None
    if len(values) < 3 or np.any(values[:3] < 1) or np.any(values[:3] != np.rint(values[:3])):
        raise ImageError(f"{path} is not a .3ddose file: the first three numbers must be the "
                         "voxel counts nx ny nz")
    n = values[:3].astype(int)
    expected = 3 + int(n.sum()) + 3 + 2 * int(np.prod(n))
    if len(values) != expected:
        raise ImageError(f"{path} holds {len(values)} numbers, a {n[0]}×{n[1]}×{n[2]} .3ddose "
                         f"needs {expected} (counts, boundaries, doses, uncertainties); the file "
                         "is truncated or not a .3ddose")
    cuts = np.cumsum([3, n[0] + 1, n[1] + 1, n[2] + 1])
    bounds = [values[cuts[a]:cuts[a + 1]] for a in range(3)]
    spacing, origin = np.empty(3), np.empty(3)
    for a, (b, name) in enumerate(zip(bounds, "xyz", strict=True)):
        step = np.diff(b)
        if np.any(step <= 0) or np.ptp(step) > UNIFORM_RTOL * step.mean():
            raise ImageError(f"{path}: the {name} voxel boundaries are not increasing in equal "
                             f"steps (steps {step.min():g}…{step.max():g} cm); tetdose needs a "
                             "uniform grid: score the dose on uniform voxels")
        spacing[a] = step.mean() * MM_PER_CM
        origin[a] = (b[0] + 0.5 * step.mean()) * MM_PER_CM
    grid = ImageGrid(origin, spacing, np.eye(3), tuple(int(v) for v in n))
    body = values[cuts[3]:]
    count = int(np.prod(n))
    return (Image(body[:count].reshape(grid.shape), grid),
            Image(body[count:].reshape(grid.shape), grid))


def write_3ddose(path: str | os.PathLike[str], dose: Image,
                 relative_uncertainty: Image | None = None) -> Path:
    """Write ``dose`` (identity direction) as a ``.3ddose`` (uncertainties 0 if not given)."""
    grid = dose.grid
    if np.abs(grid.direction - np.eye(3)).max() > 1e-9:
        raise ImageError("a .3ddose grid has the patient axes as its axes; resample the dose "
                         "onto an axis-aligned grid first")
    unc = (np.zeros(grid.shape) if relative_uncertainty is None
           else np.asarray(relative_uncertainty.array, dtype=np.float64))
    lines = [" ".join(str(v) for v in grid.size)]
    for a in range(3):
        edges = (grid.origin_mm[a] + (np.arange(grid.size[a] + 1) - 0.5) * grid.spacing_mm[a])
        lines.append(" ".join(f"{v:.17g}" for v in edges / MM_PER_CM))
    for block in (np.asarray(dose.array, dtype=np.float64), unc):
        lines.append(" ".join(f"{v:.17g}" for v in block.ravel()))
    path = Path(path)
    with atomic_write_file(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n")
    return path
