"""Signed distance fields of label masks, and their trilinear samples at points.

For a binary mask M on a voxel grid, SimpleITK's ``SignedMaurerDistanceMap`` (Maurer, Qi &
Raghavan, IEEE PAMI 25 (2003) 265–270; exact Euclidean distance in physical units) gives d(M),
which is 0 on the mask's boundary voxels and the distance to them elsewhere (negative inside).
The field used here is

    φ = (d(M) − d(¬M)) / 2                                                         [mm],

which is −½·h at a boundary voxel of M and +½·h at the face-adjacent voxel outside (h = the
spacing along that axis), so its trilinear interpolant is zero on the shared voxel face: the
voxel region's volume is kept, where d(M) alone would shrink every label by half a voxel.

Before the transform the mask is cropped to its bounding box plus ``margin_vox`` voxels (so a
small organ in a large image costs a small transform) and optionally blurred by a Gaussian
(``smoothing_vox`` voxels per axis, applied to φ) to remove the voxel staircase; the blur moves a
surface of mean curvature H by about σ²H (σ²/R for a sphere), which the volume correction in
:mod:`tetdose.meshing.levelset` takes back. Samples outside the crop take the crop's border
value (always positive: the border lies outside the label), so the sign is right everywhere.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from tetdose._typing import FloatArray
from tetdose.core.image import ImageGrid

#: Voxels of background kept around a label's bounding box before its distance transform.
MARGIN_VOX = 4


@dataclass(frozen=True, eq=False)
class DistanceField:
    """φ [mm] (negative inside) on the voxels ``lo … lo + shape − 1`` (i, j, k) of ``grid``."""

    phi_mm: np.ndarray
    lo_ijk: np.ndarray
    grid: ImageGrid

    def __call__(self, points_mm: FloatArray) -> FloatArray:
        """Trilinear interpolation of φ at patient points (N, 3) [mm]; border value outside."""
        idx = self.grid.physical_to_index(points_mm) - self.lo_ijk
        return ndimage.map_coordinates(self.phi_mm, idx[:, ::-1].T, order=1, mode="nearest")

    @property
    def max_depth_mm(self) -> float:
        """Largest distance from inside the mask to its boundary (half its thickness) [mm]."""
        return float(max(-self.phi_mm.min(), 0.0))


def _maurer(mask: np.ndarray, spacing_mm: FloatArray) -> np.ndarray:
    import SimpleITK as sitk

    img = sitk.GetImageFromArray(mask.astype(np.uint8))
    img.SetSpacing(tuple(float(s) for s in spacing_mm))
    out = sitk.SignedMaurerDistanceMap(img, insideIsPositive=False, squaredDistance=False,
                                       useImageSpacing=True)
    return sitk.GetArrayFromImage(out).astype(np.float64)


def signed_distance(mask: np.ndarray, grid: ImageGrid, *, smoothing_vox: float = 0.0,
                    margin_vox: int = MARGIN_VOX) -> DistanceField:
    """Signed distance φ [mm] of a boolean mask (numpy shape ``grid.shape``), see module doc."""
    kji = np.nonzero(mask)
    lo = np.array([a.min() for a in kji]) - margin_vox
    hi = np.array([a.max() for a in kji]) + 1 + margin_vox
    crop = np.zeros(tuple(hi - lo), dtype=bool)
    src_lo = np.maximum(lo, 0)
    src_hi = np.minimum(hi, mask.shape)
    dst = tuple(slice(a - b, c - b) for a, b, c in zip(src_lo, lo, src_hi, strict=True))
    crop[dst] = mask[tuple(slice(a, c) for a, c in zip(src_lo, src_hi, strict=True))]
    phi = 0.5 * (_maurer(crop, grid.spacing_mm) - _maurer(~crop, grid.spacing_mm))
    if smoothing_vox > 0:
        phi = ndimage.gaussian_filter(phi, smoothing_vox, mode="nearest")
    return DistanceField(phi, lo[::-1].astype(np.float64), grid)
