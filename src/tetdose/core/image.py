"""ImageGrid and Image: voxel data with SimpleITK/DICOM geometry (origin, spacing, direction).

Conventions (those of SimpleITK): ``size = (nx, ny, nz)`` counts voxels along the grid axes;
``array`` has numpy shape ``(nz, ny, nx)``; voxel ``(i, j, k)`` has its centre at
``origin + direction @ ((i, j, k) * spacing)`` [mm] and spans ±spacing/2 about it. The flat
voxel id used by the sparse overlap matrices is ``(k * ny + j) * nx + i`` (C order of ``array``).

The *grid frame* of a point is ``q = directionᵀ (p − origin)`` [mm]: a rigid change of frame in
which voxel faces are the planes ``q_a = (n − ½) spacing_a``. Volumes are invariant under it, so
every exact volume computation runs in the grid frame and honours any orthonormal direction.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from tetdose._typing import FloatArray, IntArray
from tetdose.errors import GeometryMismatchError, ImageError

#: Largest |DᵀD − I| accepted for a direction matrix.
ORTHONORMAL_TOL = 1e-6
#: CT numbers outside this range [HU] mean the image is not a CT in HU (wrapped or unscaled
#: values, densities…): air is −1000 HU, padding at most −3024 HU, dense metal about +30000 HU.
CT_HU_RANGE = (-5000.0, 40000.0)
#: A floating-point "CT" whose fractional values all lie in [0, this] is a density image [g/cm³].
DENSITY_LIKE_MAX = 3.5


@dataclass(frozen=True, eq=False)
class ImageGrid:
    """Geometry of a 3-D voxel grid: origin [mm], spacing [mm], direction cosines, size.

    Parameters
    ----------
    origin_mm : (3,) float
        Centre of voxel (0, 0, 0) in the patient frame [mm].
    spacing_mm : (3,) float
        Voxel size along the grid's axes [mm], > 0.
    direction : (3, 3) float
        Direction cosines, columns = the grid's axes in the patient frame (orthonormal).
    size : (int, int, int)
        Voxels along each axis; arrays on the grid are indexed ``[i, j, k]``.

    Raises
    ------
    ImageError
        A non-positive size or spacing, a non-finite origin, or a non-orthonormal direction.

    Examples
    --------
    >>> import numpy as np
    >>> g = ImageGrid([-10.0, -10.0, 0.0], [2.0, 2.0, 3.0], np.eye(3), (10, 10, 4))
    >>> g.voxel_volume_mm3, g.n_voxels
    (12.0, 400)
    >>> g.index_to_physical([[1, 2, 3]]).tolist()  # voxel centre [mm]
    [[-8.0, -6.0, 9.0]]
    """

    origin_mm: FloatArray
    spacing_mm: FloatArray
    direction: FloatArray
    size: tuple[int, int, int]

    def __post_init__(self) -> None:
        origin = np.asarray(self.origin_mm, dtype=np.float64).reshape(3)
        spacing = np.asarray(self.spacing_mm, dtype=np.float64).reshape(3)
        direction = np.asarray(self.direction, dtype=np.float64).reshape(3, 3)
        size = tuple(int(n) for n in self.size)
        if len(size) != 3 or min(size) < 1:
            raise ImageError(f"image size must be three positive counts, got {self.size}")
        if not (np.all(np.isfinite(spacing)) and np.all(spacing > 0)):
            raise ImageError(f"voxel spacing must be positive, got {spacing.tolist()} mm")
        if not np.all(np.isfinite(origin)):
            raise ImageError(f"image origin must be finite, got {origin.tolist()}")
        if np.abs(direction.T @ direction - np.eye(3)).max() > ORTHONORMAL_TOL:
            raise ImageError(
                "the image direction matrix is not orthonormal (sheared or scaled grid); "
                "resample the image onto an orthonormal grid first"
            )
        object.__setattr__(self, "origin_mm", origin)
        object.__setattr__(self, "spacing_mm", spacing)
        object.__setattr__(self, "direction", direction)
        object.__setattr__(self, "size", size)

    @property
    def shape(self) -> tuple[int, int, int]:
        """Numpy shape of the voxel array, (nz, ny, nx)."""
        return self.size[2], self.size[1], self.size[0]

    @property
    def n_voxels(self) -> int:
        return int(np.prod(self.size))

    @property
    def voxel_volume_mm3(self) -> float:
        return float(np.prod(self.spacing_mm))

    @cached_property
    def affine(self) -> FloatArray:
        """4×4 matrix mapping homogeneous voxel indices (i, j, k, 1) to patient mm."""
        a = np.eye(4)
        a[:3, :3] = self.direction * self.spacing_mm[None, :]
        a[:3, 3] = self.origin_mm
        return a

    def to_grid_frame(self, points_mm: FloatArray) -> FloatArray:
        """Patient points [mm] → grid-frame coordinates q = Dᵀ(p − origin) [mm]."""
        return _times_3x3(np.asarray(points_mm, dtype=np.float64) - self.origin_mm, self.direction)

    def index_to_physical(self, index: FloatArray) -> FloatArray:
        """Continuous voxel indices (…, 3) in (i, j, k) order → patient points [mm]."""
        scaled = self.direction.T * self.spacing_mm[:, None]  # row a = spacing_a · column a of D
        return _times_3x3(np.asarray(index, dtype=np.float64), scaled) + self.origin_mm

    def physical_to_index(self, points_mm: FloatArray) -> FloatArray:
        """Patient points [mm] → continuous voxel indices (i, j, k)."""
        return self.to_grid_frame(points_mm) / self.spacing_mm

    def voxel_index(self, points_mm: FloatArray) -> IntArray:
        """(…, 3) integer index (i, j, k) of the voxel holding each point [mm] (may lie off the
        grid): ⌊x + ½⌋ of the continuous index, the rule of :meth:`voxel_of`."""
        return np.floor(self.physical_to_index(points_mm) + 0.5).astype(np.int64)

    def voxel_of(self, points_mm: FloatArray) -> IntArray:
        """Flat id of the voxel containing each patient point [mm], −1 off the grid.

        Voxel i spans continuous indices [i − ½, i + ½), so i = ⌊x + ½⌋ per axis: a point on a
        face between two voxels goes to the upper one (not numpy's rint, which rounds halves to
        even and so splits face points between the two sides). The one rounding rule of tetdose,
        the same as the overlap kernels' voxel ranges.
        """
        idx = self.voxel_index(points_mm).reshape(-1, 3)
        size = np.array(self.size)
        ok = np.all((idx >= 0) & (idx < size), axis=1)
        flat = (idx[:, 2] * size[1] + idx[:, 1]) * size[0] + idx[:, 0]
        return np.where(ok, flat, -1)

    def voxel_centers_mm(self) -> FloatArray:
        """(n_voxels, 3) centres [mm] in flat voxel-id order."""
        k, j, i = np.meshgrid(*(np.arange(n) for n in self.shape), indexing="ij")
        idx = np.stack([i.ravel(), j.ravel(), k.ravel()], axis=1).astype(np.float64)
        return self.index_to_physical(idx)

    def bounds_grid_frame(self) -> tuple[FloatArray, FloatArray]:
        """Grid-frame box [mm] covered by the voxels (outer faces)."""
        return -0.5 * self.spacing_mm, (np.array(self.size) - 0.5) * self.spacing_mm

    def same_as(self, other: ImageGrid, *, tol_mm: float = 1e-4) -> bool:
        return (
            self.size == other.size
            and np.allclose(self.origin_mm, other.origin_mm, atol=tol_mm, rtol=0)
            and np.allclose(self.spacing_mm, other.spacing_mm, atol=tol_mm, rtol=0)
            and np.allclose(self.direction, other.direction, atol=1e-6, rtol=0)
        )

    def require_same(self, other: ImageGrid, what: str = "images") -> None:
        if not self.same_as(other):
            raise GeometryMismatchError(
                f"{what} are not on the same grid (size {self.size} vs {other.size}, origin "
                f"{self.origin_mm.tolist()} vs {other.origin_mm.tolist()}); resample one onto "
                "the other first"
            )


def _times_3x3(x: FloatArray, m: FloatArray) -> FloatArray:
    """x @ m for (…, 3) points and a 3×3 matrix, as three broadcast multiply-adds.

    Faster than a BLAS product with inner dimension 3 for millions of points, and immune to BLAS
    thread oversubscription (measured 0.11 s vs 0.005 s per million points on a busy machine).
    """
    return x[..., 0:1] * m[0] + x[..., 1:2] * m[1] + x[..., 2:3] * m[2]


@dataclass(frozen=True, eq=False)
class Image:
    """A scalar image: ``array`` of numpy shape (nz, ny, nx) on ``grid``."""

    array: np.ndarray
    grid: ImageGrid

    def __post_init__(self) -> None:
        arr = np.asarray(self.array)
        if arr.shape != self.grid.shape:
            raise ImageError(f"array shape {arr.shape} does not match grid shape {self.grid.shape}")
        object.__setattr__(self, "array", arr)

    def with_array(self, array: np.ndarray) -> Image:
        """The same grid with new voxel values."""
        return Image(np.asarray(array), self.grid)

    def to_sitk(self):  # noqa: ANN201 - SimpleITK type
        import SimpleITK as sitk

        img = sitk.GetImageFromArray(np.ascontiguousarray(self.array))
        img.SetOrigin(tuple(self.grid.origin_mm))
        img.SetSpacing(tuple(self.grid.spacing_mm))
        img.SetDirection(tuple(self.grid.direction.ravel()))
        return img

    @staticmethod
    def from_sitk(img) -> Image:  # noqa: ANN001 - SimpleITK type
        import SimpleITK as sitk

        if img.GetDimension() != 3:
            raise ImageError(f"expected a 3-D image, got {img.GetDimension()}-D")
        if img.GetNumberOfComponentsPerPixel() != 1:
            raise ImageError(f"expected a scalar image, got {img.GetNumberOfComponentsPerPixel()} "
                             "values per voxel; give a 3-D image with one value per voxel")
        grid = ImageGrid(img.GetOrigin(), img.GetSpacing(), img.GetDirection(), img.GetSize())
        return Image(sitk.GetArrayFromImage(img), grid)


def check_ct_hu(image: Image, source: str = "the CT") -> Image:
    """Refuse an image that cannot be a CT in Hounsfield units; return it unchanged.

    A CT holds signed HU (air ≈ −1000): unsigned or 8-bit pixel types (negative HU wrapped,
    RescaleIntercept not applied), NaN or infinite voxels, and values outside
    :data:`CT_HU_RANGE` are refused with what was found.
    """
    arr = image.array
    dtype = arr.dtype
    if not np.issubdtype(dtype, np.number) or np.iscomplexobj(arr) or dtype == np.bool_:
        raise ImageError(f"{source} holds {dtype} values; a CT must hold signed HU numbers")
    lo, hi = (float(arr.min()), float(arr.max())) if np.issubdtype(dtype, np.integer) else \
        (float(np.nanmin(arr)), float(np.nanmax(arr))) if np.isfinite(arr).any() else (0.0, 0.0)
    if np.issubdtype(dtype, np.unsignedinteger) or dtype == np.int8:
        raise ImageError(
            f"{source} has pixel type {dtype} (values {lo:g}…{hi:g}), which cannot hold the CT "
            "range (air −1000 HU): negative HU were wrapped or RescaleIntercept was not "
            "applied; store it as signed HU (e.g. int16) first"
        )
    if np.issubdtype(dtype, np.floating):
        bad = ~np.isfinite(arr)
        if bad.any():
            k, j, i = (int(a[0]) for a in np.nonzero(bad))
            raise ImageError(
                f"{source} has {int(bad.sum())} NaN or infinite voxel(s) (first at voxel "
                f"i={i}, j={j}, k={k}); replace them with a CT number (e.g. −1000 HU for air)"
            )
    if lo < CT_HU_RANGE[0] or hi > CT_HU_RANGE[1]:
        raise ImageError(
            f"{source} holds values {lo:g}…{hi:g}, outside the HU range of a CT "
            f"({CT_HU_RANGE[0]:g}…{CT_HU_RANGE[1]:g}): give a CT in Hounsfield units (wrapped or "
            "unscaled pixel values, or densities, are not)"
        )
    if (np.issubdtype(dtype, np.floating) and 0.0 <= lo and hi <= DENSITY_LIKE_MAX
            and hi > lo and np.any(arr != np.round(arr))):
        raise ImageError(
            f"{source} holds fractional values {lo:.4g}…{hi:.4g}: a density image [g/cm³], not "
            "HU (a CT in HU spans tens to thousands of HU, air −1000); give the CT in Hounsfield "
            "units (`tetdose voxelize --hu` writes one from a mapped mesh)"
        )
    return image
