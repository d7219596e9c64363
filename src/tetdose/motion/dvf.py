"""Displacement-field images (DVF) as written by ITK, elastix/transformix and plastimatch.

Convention (stated once, used everywhere): a DVF of phase t is a 3-component vector image on
its own grid whose vectors are **physical displacements in mm in the patient frame** (ITK's
convention: not index-space, not scaled by spacing) and which maps **reference points to
phase points**:

    p_t = p_0 + u(p_0).

This is what a registration with the reference CT as the *fixed* image and phase t as the
*moving* image produces (elastix/transformix ``-def all``, plastimatch ``--output-vf``): ITK
transforms map fixed-image points to moving-image points.

Mesh vertices are moved with ``u`` interpolated trilinearly at the vertex, in the DVF's grid
frame (origin, spacing and direction honoured: index = Dᵀ(p − origin)/spacing), so an affine
displacement field is reproduced exactly. A vertex outside the DVF's voxel-centre box cannot be
interpolated and is an error (no extrapolation).

Images (the CT outside the mesh) are warped by the pull-back ``I_t(x) = I_0(x + v(x))`` with
the inverse field ``v`` (phase → reference), computed by SimpleITK's
``InvertDisplacementField`` (fixed-point iteration v ← −u(x + v), Christensen & Johnson 2001),
so that image and mesh move consistently: ``v(p_0 + u(p_0)) = −u(p_0)`` to the solver tolerance.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tetdose._typing import FloatArray
from tetdose.core.image import Image, ImageGrid
from tetdose.errors import GeometryMismatchError, ImageError

#: Tolerance on the DVF cover test, in voxels (points this close outside the box are clamped).
COVER_TOL_VOXELS = 1e-6
#: Iterations and tolerances [mm] of the fixed-point inversion of a DVF.
INVERT_ITERATIONS = 50
INVERT_MAX_ERROR_MM = 1e-3


@dataclass(frozen=True, eq=False)
class DisplacementField:
    """A displacement field ``vectors_mm`` of numpy shape (nz, ny, nx, 3) [mm] on ``grid``."""

    vectors_mm: FloatArray
    grid: ImageGrid

    def __post_init__(self) -> None:
        v = np.ascontiguousarray(self.vectors_mm, dtype=np.float64)
        if v.shape != (*self.grid.shape, 3):
            raise ImageError(f"displacement array has shape {v.shape}, expected "
                             f"{(*self.grid.shape, 3)} (3 components per voxel)")
        if not np.isfinite(v).all():
            raise ImageError("the displacement field holds NaN or infinite vectors")
        object.__setattr__(self, "vectors_mm", v)

    def at(self, points_mm: FloatArray, *, what: str = "points") -> FloatArray:
        """Trilinear displacement [mm] at (P, 3) patient points; error if any lies outside."""
        pts = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
        idx = self.grid.physical_to_index(pts)
        hi = np.array(self.grid.size, dtype=np.float64) - 1.0
        out = np.any((idx < -COVER_TOL_VOXELS) | (idx > hi + COVER_TOL_VOXELS), axis=1)
        if out.any():
            lo_mm, hi_mm = self.grid.origin_mm, self.grid.index_to_physical(hi)
            raise GeometryMismatchError(
                f"the displacement field does not cover {int(out.sum())} of {len(pts)} {what} "
                f"(first ids {np.flatnonzero(out)[:10].tolist()}); its voxel centres span "
                f"{lo_mm.round(2).tolist()} … {hi_mm.round(2).tolist()} mm — compute the DVF on "
                "a grid that contains the whole mesh (e.g. the reference CT's grid)"
            )
        idx = np.clip(idx, 0.0, hi)
        base = np.minimum(np.floor(idx), np.maximum(hi - 1.0, 0.0)).astype(np.intp)
        frac = idx - base
        nz, ny, nx = self.grid.shape
        flat = self.vectors_mm.reshape(-1, 3)
        result = np.zeros((len(pts), 3))
        for corner in range(8):
            d = np.array([(corner >> a) & 1 for a in range(3)])
            c = np.minimum(base + d, hi.astype(np.intp))
            w = np.prod(np.where(d == 1, frac, 1.0 - frac), axis=1)
            result += w[:, None] * flat[(c[:, 2] * ny + c[:, 1]) * nx + c[:, 0]]
        return result

    def moved(self, points_mm: FloatArray) -> FloatArray:
        """Phase positions p + u(p) [mm] of reference points (P, 3)."""
        pts = np.asarray(points_mm, dtype=np.float64)
        return pts + self.at(pts, what="mesh vertices")

    def to_sitk(self):  # noqa: ANN201 - SimpleITK type
        import SimpleITK as sitk

        img = sitk.GetImageFromArray(self.vectors_mm, isVector=True)
        img.SetOrigin(tuple(self.grid.origin_mm))
        img.SetSpacing(tuple(self.grid.spacing_mm))
        img.SetDirection(tuple(self.grid.direction.ravel()))
        return img

    def inverse(self) -> DisplacementField:
        """The inverse field v (phase → reference), on the same grid (see module docstring)."""
        import SimpleITK as sitk

        inv = sitk.InvertDisplacementField(
            self.to_sitk(), maximumNumberOfIterations=INVERT_ITERATIONS,
            maxErrorToleranceThreshold=INVERT_MAX_ERROR_MM,
            meanErrorToleranceThreshold=INVERT_MAX_ERROR_MM / 10, enforceBoundaryCondition=False)
        return DisplacementField(sitk.GetArrayFromImage(inv), self.grid)


def read_dvf(path: str | os.PathLike[str]) -> DisplacementField:
    """Read a 3-component displacement image (NRRD, MHA, NIfTI …) with SimpleITK."""
    import SimpleITK as sitk

    path = Path(path)
    if not path.exists():
        raise ImageError(f"displacement field {path} does not exist")
    try:
        img = sitk.ReadImage(str(path))
    except RuntimeError as exc:
        raise ImageError(f"cannot read displacement field {path}: "
                         f"{str(exc).strip().splitlines()[-1]}") from exc
    if img.GetDimension() != 3 or img.GetNumberOfComponentsPerPixel() != 3:
        raise ImageError(
            f"{path} is a {img.GetDimension()}-D image with {img.GetNumberOfComponentsPerPixel()}"
            " component(s) per voxel; a DVF must be 3-D with 3 components (dx, dy, dz in mm)"
        )
    grid = ImageGrid(img.GetOrigin(), img.GetSpacing(), img.GetDirection(), img.GetSize())
    return DisplacementField(sitk.GetArrayFromImage(img).astype(np.float64), grid)


def write_dvf(path: str | os.PathLike[str], field: DisplacementField) -> Path:
    """Write a displacement field as a float64 vector image (format from the extension); atomic."""
    import SimpleITK as sitk

    from tetdose._atomic import atomic_write_file

    path = Path(path)
    with atomic_write_file(path) as tmp:
        sitk.WriteImage(field.to_sitk(), str(tmp), True)
    return path


def warp_image(image: Image, field: DisplacementField, *, outside_value: float) -> Image:
    """Reference image → phase image by pull-back I_t(x) = I_0(x + v(x)), v = inverse of u.

    Trilinear interpolation of ``image`` (SimpleITK ``Resample``) on its own grid; points
    pulled back outside the image take ``outside_value``. Outside the DVF grid v = 0.
    """
    import SimpleITK as sitk

    inv = field.inverse().to_sitk()
    transform = sitk.DisplacementFieldTransform(sitk.Cast(inv, sitk.sitkVectorFloat64))
    src = image.with_array(np.asarray(image.array, dtype=np.float64)).to_sitk()
    out = sitk.Resample(src, src, transform, sitk.sitkLinear, float(outside_value),
                        sitk.sitkFloat64)
    return Image(sitk.GetArrayFromImage(out), image.grid)
