"""A tilted or sheared slice stack (gantry tilt) resampled onto an orthogonal grid.

Voxel (i, j, k) of such a stack lies at x = P₀ + i·Δc·r + j·Δr·c + k·s [mm] (DICOM PS3.3
C.7.6.2.1.1: r, c the ImageOrientationPatient row and column cosines, Δc, Δr the column and
row pixel spacing; s the step between successive ImagePositionPatient along the stack). When s
is not along r × c, or r ⟂ c fails, no orthonormal grid holds the voxels, so the values are
resampled: the output grid has orthonormal axes u = r/|r|, v = (c − (c·u)u)/|…|, n = u × v,
in-plane spacing Δc, Δr, slice spacing |s·n|, and covers the stack's bounding box in that frame.
Each output voxel centre x is mapped back to stack indices (i, j, k) = A⁻¹(x − P₀), with
A = [Δc r | Δr c | s], and the stack is interpolated there (SimpleITK linear); outside the stack,
``outside_hu`` (air, −1000 HU, by default).
"""

from __future__ import annotations

import numpy as np

from tetdose._typing import FloatArray
from tetdose.core.image import Image, ImageGrid
from tetdose.errors import ImageError

#: Value of output voxels outside the tilted stack [HU] (air).
OUTSIDE_HU = -1000.0
#: Largest deviation of a slice position from the straight line through the stack [mm].
LINE_TOL_MM = 0.01


def stack_affine(positions_mm: FloatArray, row: FloatArray, col: FloatArray,
                 pixel_spacing_mm: tuple[float, float]) -> tuple[FloatArray, FloatArray]:
    """(A, P₀): index (i, j, k) → x = P₀ + A @ (i, j, k) [mm] of slices at ``positions_mm``
    (K, 3), in stack order; refuses positions off one straight, uniform line."""
    pos = np.asarray(positions_mm, dtype=np.float64)
    r = np.asarray(row, dtype=np.float64) / np.linalg.norm(row)
    c = np.asarray(col, dtype=np.float64) / np.linalg.norm(col)
    k = np.arange(len(pos))
    step = (pos[-1] - pos[0]) / max(len(pos) - 1, 1)
    off = np.abs(pos - (pos[0] + np.outer(k, step))).max()
    if off > LINE_TOL_MM:
        raise ImageError(f"slice positions leave a straight, uniform line by {off:.3g} mm; "
                         "the stack cannot be resampled — export the series again")
    # DICOM PixelSpacing = (between rows, along c; between columns, along r)
    between_rows, between_columns = pixel_spacing_mm
    a = np.column_stack([between_columns * r, between_rows * c, step])
    if abs(np.linalg.det(a)) < 1e-9:
        raise ImageError("the slices lie in one plane; the stack has no volume")
    return a, pos[0]


def orthogonal_grid(a: FloatArray, p0: FloatArray, shape_kji: tuple[int, int, int]) -> ImageGrid:
    """The orthonormal grid (module docstring) covering the stack x = p0 + A @ (i, j, k)."""
    u = a[:, 0] / np.linalg.norm(a[:, 0])
    v = a[:, 1] - (a[:, 1] @ u) * u
    v /= np.linalg.norm(v)
    n = np.cross(u, v)
    if a[:, 2] @ n < 0:
        n = -n
    frame = np.column_stack([u, v, n])
    spacing = np.array([np.linalg.norm(a[:, 0]), np.linalg.norm(a[:, 1]), abs(a[:, 2] @ n)])
    nk, nj, ni = shape_kji
    corners = np.array([[i, j, k] for i in (0, ni - 1) for j in (0, nj - 1) for k in (0, nk - 1)],
                       dtype=np.float64)
    local = (p0 + corners @ a.T) @ frame  # corner voxel centres in the (u, v, n) frame
    lo, hi = local.min(axis=0), local.max(axis=0)
    size = np.floor((hi - lo) / spacing + 1e-6).astype(int) + 1
    return ImageGrid(frame @ lo, spacing, frame, tuple(int(s) for s in size))


def resample_stack(array_kji: np.ndarray, a: FloatArray, p0: FloatArray, *,
                   outside_hu: float = OUTSIDE_HU) -> Image:
    """The stack ``array_kji`` (voxel (i, j, k) at p0 + A @ (i, j, k)) on its
    :func:`orthogonal_grid`, linear interpolation, ``outside_hu`` outside (float32)."""
    import SimpleITK as sitk

    grid = orthogonal_grid(a, p0, array_kji.shape)
    stack = sitk.GetImageFromArray(np.asarray(array_kji, dtype=np.float32))  # index = physical
    inv = np.linalg.inv(a)
    to_index = sitk.AffineTransform(inv.ravel().tolist(), (-inv @ p0).tolist())
    reference = Image(np.zeros(grid.shape, np.float32), grid).to_sitk()
    out = sitk.Resample(stack, reference, to_index, sitk.sitkLinear, float(outside_hu),
                        sitk.sitkFloat32)
    return Image(sitk.GetArrayFromImage(out), grid)
