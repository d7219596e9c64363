"""Deformable registration of 4D-CT phases: reference phase → each phase, as DVF images [mm].

The result follows :mod:`tetdose.motion.dvf`: the reference CT is the *fixed* image and phase t
the *moving* one, so the field u maps reference points to phase points, p_t = p_0 + u(p_0), and
the phase CT pulled back by it, I_t(x + u(x)), matches the reference I_0(x).

Two SimpleITK methods, both multi-resolution (coarse → fine on a Gaussian pyramid), both with a
mono-modal metric (same scanner, same HU: squared intensity difference):

* ``"demons"`` (default): symmetric-forces demons (Thirion 1998; Vercauteren et al. 2009 for the
  symmetric/ESM forces, ``FastSymmetricForcesDemonsRegistrationFilter``), u ← G_σ * (u + δu) at
  every iteration, the field of one level upsampled as the start of the next. Intensities are
  clipped to [−1000, 1000] HU (dense bone would otherwise dominate the forces) and voxels outside
  the mask set to −1000 HU in both images, so only the body drives the field (the body mask is
  each image's own; a given mask is widened by 15 mm and applied to both alike). Only the
  bounding box of the two masks widened by ``crop_margin_mm`` is registered (outside the masks
  both images are a constant −1000 HU, where the forces vanish); the field is pasted back and
  continued outside the box by edge replication (each outside voxel takes the value of the
  nearest voxel of the box), which keeps it continuous. In a 4D-CT the phases are registered
  outward from the reference, each started from its neighbour's field (``warm_start``).
* ``"bspline"``: a cubic B-spline transform (control points every ``grid_spacing_mm`` at the
  finest level, refined ×2 per level), mean-squares metric restricted to the mask, L-BFGS-B.

Which is the default was decided by measurement (``tests/verification/test_register.py`` and
``bench/bench_register.py``; figures in bench/README.md): on the real lung CT warped by known
breathing fields the demons field is as accurate and several times faster.

Quality per phase (:class:`RegistrationReport`): the metric (mean squared HU difference inside
the mask) before and after; the Jacobian determinant det(I + ∇u) range inside the mask
(``DisplacementFieldJacobianDeterminant``), where det ≤ 0 is folding — an invalid field, reported
with its fraction and the worst voxel's position; optionally the inverse consistency
|u(x) + w(x + u(x))| [mm] of the forward field u and the separately registered backward field w
(doubles the time, hence off by default); and the wall time.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import NamedTuple

import numpy as np
from tqdm import tqdm

from tetdose.core.body import largest_component
from tetdose.core.image import Image
from tetdose.errors import ImageError
from tetdose.motion.dvf import DisplacementField

METHODS = ("demons", "bspline")
#: Body mask: voxels above this CT number [HU] (largest connected component, holes filled).
BODY_THRESHOLD_HU = -400.0
#: In-plane pixel size [mm] the body mask is computed at (a sub-sampled slice; fine enough).
BODY_MASK_PIXEL_MM = 3.0
#: Fraction of the mask voxels sampled by the B-spline metric at each evaluation.
BSPLINE_SAMPLING = 0.2
#: A given mask is widened by this margin [mm] (more than breathing motion) for demons.
MASK_MARGIN_MM = 15.0
#: Intensity window [HU] the demons forces see.
DEMONS_CLIP_HU = (-1000.0, 1000.0)


@dataclass(frozen=True)
class RegistrationSettings:
    """Parameters of :func:`register`.

    ``shrink``: pyramid levels as shrink factors (coarse → fine, on the finest spacing);
    ``iterations``: per level; ``smoothing_mm``: demons field regularisation σ [mm];
    ``grid_spacing_mm``: B-spline control-point spacing at the finest level [mm];
    ``min_spacing_mm``: demons: the finest level's voxels are at least this size [mm] (a clinical
    0.98 mm CT is registered at 2 mm — 4× fewer voxels — and the field resampled back);
    ``threads``: SimpleITK threads (None: SimpleITK's default, all cores);
    ``crop_margin_mm``: demons: register inside the bounding box of the two images' masks
    widened by this margin [mm], not the whole image (None: the whole image); outside the box
    the field is continued by its value on the nearest face of the box (edge replication);
    ``warm_start``: demons: :func:`register_4dct` registers outward from the reference and starts
    each phase from the field of its neighbour nearer the reference, skipping the coarsest level.

    The defaults before the speed-up (bench/README.md) were ``iterations=(100, 60, 40)``,
    ``crop_margin_mm=None``, ``warm_start=False`` (:data:`BEFORE_SPEEDUP`).
    """

    method: str = "demons"
    shrink: tuple[int, ...] = (4, 2, 1)
    iterations: tuple[int, ...] = (50, 30, 30)
    smoothing_mm: float = 5.0
    grid_spacing_mm: float = 30.0
    min_spacing_mm: float = 2.0
    threads: int | None = None
    crop_margin_mm: float | None = 20.0
    warm_start: bool = True

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ImageError(f"registration method must be one of {METHODS}, got {self.method!r}")
        if len(self.shrink) != len(self.iterations) or not self.shrink:
            raise ImageError(f"{len(self.shrink)} pyramid levels but {len(self.iterations)} "
                             "iteration counts; give one per level")
        if min(self.shrink) < 1 or min(self.iterations) < 1:
            raise ImageError("shrink factors and iterations must be ≥ 1")
        if min(self.smoothing_mm, self.grid_spacing_mm, self.min_spacing_mm) <= 0:
            raise ImageError("smoothing_mm, grid_spacing_mm and min_spacing_mm must be > 0")
        if self.crop_margin_mm is not None and self.crop_margin_mm < 0:
            raise ImageError("crop_margin_mm must be ≥ 0 (or None: no crop)")


#: The demons settings before the speed-up (issue 12's first figures), for the bench's A/B.
BEFORE_SPEEDUP = RegistrationSettings(iterations=(100, 60, 40), crop_margin_mm=None,
                                      warm_start=False)


@dataclass(frozen=True)
class RegistrationReport:
    """Quality of one registered phase (see module docstring); lengths in mm, HU² for metrics."""

    percent: float
    metric_before_hu2: float
    metric_after_hu2: float
    jacobian_min: float
    jacobian_max: float
    folding_fraction: float
    worst_jacobian_mm: tuple[float, float, float]
    max_displacement_mm: float
    seconds: float
    inverse_consistency_mean_mm: float | None = None
    inverse_consistency_max_mm: float | None = None
    notes: list[str] = field(default_factory=list)

    @property
    def folded(self) -> bool:
        return self.folding_fraction > 0.0

    def line(self) -> str:
        ic = ("" if self.inverse_consistency_mean_mm is None else
              f", inverse consistency {self.inverse_consistency_mean_mm:.2f} mm mean / "
              f"{self.inverse_consistency_max_mm:.2f} mm max")
        return (f"phase {self.percent:g} %: metric {self.metric_before_hu2:.4g} → "
                f"{self.metric_after_hu2:.4g} HU², det J {self.jacobian_min:.3f}…"
                f"{self.jacobian_max:.3f}, max |u| {self.max_displacement_mm:.2f} mm{ic}, "
                f"{self.seconds:.1f} s")

    def folding_message(self) -> str:
        x, y, z = self.worst_jacobian_mm
        return (f"phase {self.percent:g} %: the field folds (det J ≤ 0) in "
                f"{100 * self.folding_fraction:.3g} % of the mask, worst det J "
                f"{self.jacobian_min:.3f} at ({x:.1f}, {y:.1f}, {z:.1f}) mm — raise the "
                "smoothing (--smoothing-mm) or give a mask")

    def as_dict(self) -> dict:
        return asdict(self)


def body_mask(ct_hu: Image, threshold_hu: float = BODY_THRESHOLD_HU) -> np.ndarray:
    """Boolean body mask: the convex hull, slice by slice, of the largest 3-D component > threshold.

    Slices are taken along the third grid axis (axial for a CT). The hull, rather than hole
    filling, keeps the lungs inside the body also when they touch the edge of a cropped image.
    Computed on pixels of about :data:`BODY_MASK_PIXEL_MM` (every n-th row and column) and
    expanded back: 40 → ~5 s on a 512×512×100 CT.
    """
    from scipy import ndimage
    from scipy.spatial import ConvexHull, QhullError

    step = max(1, int(BODY_MASK_PIXEL_MM // float(min(ct_hu.grid.spacing_mm[:2]))))
    above = np.asarray(ct_hu.array)[:, ::step, ::step] > threshold_hu
    body = largest_component(above, f"{threshold_hu:g} HU")
    ny, nx = body.shape[1:]
    jj, ii = np.mgrid[0:ny, 0:nx]
    pix = np.stack([ii.ravel(), jj.ravel()], axis=1).astype(np.float64)  # (i, j) per pixel
    out = np.zeros_like(body)
    for k, sl in enumerate(body):
        edge = sl & ~ndimage.binary_erosion(sl)
        pts = pix[edge.ravel()]
        if len(pts) < 3:
            out[k] = sl
            continue
        try:
            eq = ConvexHull(pts).equations
        except QhullError:  # all on a line
            out[k] = sl
            continue
        out[k] = _hull_rows(eq, ny, nx) | sl
    if step > 1:  # back to full resolution (nearest): each coarse pixel covers step × step
        nz, fy, fx = ct_hu.grid.shape
        out = np.repeat(np.repeat(out, step, axis=1), step, axis=2)[:, :fy, :fx]
    return out


def _hull_rows(eq: np.ndarray, ny: int, nx: int) -> np.ndarray:
    """Pixels (i, j) with a·i + b·j + c ≤ 0.5 for every hull facet (a, b, c) of ``eq``, row by
    row: in row j the facets with a > 0 bound i from above by (0.5 − c − b·j)/a, those with a < 0
    from below, those with a = 0 keep the row or drop it (ny × facets work, not ny × nx × facets).
    """
    a, b, c = eq[:, 0], eq[:, 1], eq[:, 2]
    r = 0.5 - c[None, :] - b[None, :] * np.arange(ny, dtype=np.float64)[:, None]  # (ny, F)
    with np.errstate(divide="ignore", invalid="ignore"):
        bound = r / a[None, :]
    hi = np.min(np.where(a > 0, bound, np.inf), axis=1)
    lo = np.max(np.where(a < 0, bound, -np.inf), axis=1)
    keep = np.all((a != 0) | (r >= 0), axis=1)
    i = np.arange(nx, dtype=np.float64)
    return keep[:, None] & (i[None, :] >= lo[:, None]) & (i[None, :] <= hi[:, None])


def register(reference: Image, phase: Image, *, mask: np.ndarray | None = None,
             settings: RegistrationSettings | None = None, percent: float = float("nan"),
             inverse_consistency: bool = False, initial: DisplacementField | None = None,
             body: np.ndarray | None = None) -> tuple[DisplacementField, RegistrationReport]:
    """Register ``phase`` (moving) to ``reference`` (fixed); the field lives on the reference grid.

    ``mask``: boolean array on the reference grid (default :func:`body_mask`). The phase is
    resampled onto the reference grid first (trilinear) if its grid differs. ``initial``: a field
    on the reference grid to start from (demons; e.g. a neighbouring phase's), the coarsest
    pyramid level is then skipped; ``body``: the reference's :func:`body_mask` if already
    computed (used when ``mask`` is None).
    """
    import SimpleITK as sitk

    s = settings or RegistrationSettings()
    if s.threads is not None:
        sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(int(s.threads))
    given = mask is not None
    if mask is None:
        mask = body_mask(reference) if body is None else np.asarray(body, dtype=bool)
    else:
        mask = np.asarray(mask, dtype=bool)
    if mask.shape != reference.grid.shape:
        raise ImageError(f"mask shape {mask.shape} differs from the reference CT's "
                         f"{reference.grid.shape}; resample it onto the reference grid")
    if not mask.any():
        raise ImageError("the registration mask holds no voxel")
    if initial is not None and not initial.grid.same_as(reference.grid):
        raise ImageError("the initial field must lie on the reference CT's grid")
    fixed = _float(reference)
    moving = _float(phase)
    if not phase.grid.same_as(reference.grid):
        moving = sitk.Resample(moving, fixed, sitk.Transform(), sitk.sitkLinear, -1000.0)
    t0 = time.perf_counter()
    u = _run(fixed, moving, mask, s, given, initial)
    seconds = time.perf_counter() - t0
    report = _report(fixed, moving, mask, u, reference, percent, seconds)
    if inverse_consistency:
        w = _run(moving, fixed, mask if given else _moving_mask(moving, mask), s, given)
        report = _with_inverse_consistency(report, u, w, mask, reference)
    return u, report


def register_4dct(phases: Sequence[Image], reference_index: int, *,
                  percents: Sequence[float] | None = None, mask: np.ndarray | None = None,
                  settings: RegistrationSettings | None = None,
                  inverse_consistency: bool = False,
                  progress: bool = False) -> list[tuple[DisplacementField, RegistrationReport]]:
    """One (field, report) per phase, reference → phase; the reference's own field is zero.

    With ``settings.warm_start`` the phases are registered outward from the reference (k = r±1,
    r±2, …), each started from the field of its neighbour nearer the reference: consecutive
    phases of a breathing cycle differ by a fraction of the motion, so fewer iterations remain.
    """
    if not 0 <= reference_index < len(phases):
        raise ImageError(f"reference phase index {reference_index} outside 0…{len(phases) - 1}")
    s = settings or RegistrationSettings()
    pct = list(percents) if percents is not None else [100.0 * k / len(phases)
                                                        for k in range(len(phases))]
    ref = phases[reference_index]
    body = body_mask(ref) if mask is None else None  # once, not once per phase
    out: dict[int, tuple[DisplacementField, RegistrationReport]] = {}
    zero = DisplacementField(np.zeros((*ref.grid.shape, 3)), ref.grid)
    out[reference_index] = (zero, _identity_report(pct[reference_index]))
    order = sorted((k for k in range(len(phases)) if k != reference_index),
                   key=lambda k: (abs(k - reference_index), k))
    for k in tqdm(order, desc="registration", unit="phase", disable=not progress):
        near = k - 1 if k > reference_index else k + 1  # neighbour nearer the reference
        initial = out[near][0] if s.warm_start and s.method == "demons" and near in out \
            and near != reference_index else None
        out[k] = register(ref, phases[k], mask=mask, settings=s, percent=pct[k],
                          inverse_consistency=inverse_consistency, initial=initial, body=body)
    return [out[k] for k in range(len(phases))]


# --- the two methods ----------------------------------------------------------------------------


def _run(fixed, moving, mask: np.ndarray, s: RegistrationSettings,  # noqa: ANN001
         given: bool, initial: DisplacementField | None = None) -> DisplacementField:
    if s.method == "demons":
        return _demons(fixed, moving, mask, s, given, initial)
    return _bspline(fixed, moving, mask, s, given)


def _float(image: Image):  # noqa: ANN202 - SimpleITK image
    return image.with_array(np.asarray(image.array, dtype=np.float32)).to_sitk()


def _mask_image(mask: np.ndarray, like):  # noqa: ANN001, ANN202
    import SimpleITK as sitk

    m = sitk.GetImageFromArray(mask.astype(np.uint8))
    m.CopyInformation(like)
    return m


def _moving_mask(moving, fixed_mask: np.ndarray) -> np.ndarray:  # noqa: ANN001
    """Mask of the moving image for the backward registration: its own body (or the fixed mask)."""
    try:
        return body_mask(Image.from_sitk(moving))
    except ImageError:
        return fixed_mask


def _level_grid(image, shrink: int, min_spacing_mm: float = 0.0):  # noqa: ANN001, ANN202
    """``image`` smoothed (σ = half the new voxel) and shrunk to voxels of about ``shrink`` ×
    max(finest spacing, ``min_spacing_mm``) along every axis (near-isotropic levels)."""
    import SimpleITK as sitk

    spacing = np.array(image.GetSpacing())
    base = max(float(spacing.min()), min_spacing_mm)
    factors = [max(1, int(round(shrink * base / sp))) for sp in spacing]
    if max(factors) == 1:
        return image
    sigma = [0.5 * f * sp for f, sp in zip(factors, spacing, strict=True)]
    smooth = sitk.SmoothingRecursiveGaussian(image, sigma)
    return sitk.Shrink(smooth, factors)


def _demons(fixed, moving, mask: np.ndarray, s: RegistrationSettings,  # noqa: ANN001
            given: bool, initial: DisplacementField | None = None) -> DisplacementField:
    """Multi-resolution demons. The body mask is each image's own (skin is an edge in both); a
    given mask is dilated by :data:`MASK_MARGIN_MM` and applied to both images alike, so that
    tissue moving across its border stays visible and identical images stay identical.
    ``initial``: a field on the fixed grid to start from (resampled onto the first level)."""
    import SimpleITK as sitk
    from scipy import ndimage

    lo, hi = DEMONS_CLIP_HU
    if given:
        radius = np.ceil(MASK_MARGIN_MM / np.array(fixed.GetSpacing())[::-1]).astype(int)
        zz, yy, xx = np.ogrid[tuple(slice(-r, r + 1) for r in radius)]
        ball = (zz / max(radius[0], 1)) ** 2 + (yy / max(radius[1], 1)) ** 2 + \
            (xx / max(radius[2], 1)) ** 2 <= 1.0
        fixed_mask = moving_mask = ndimage.binary_dilation(mask, structure=ball)
    else:
        fixed_mask, moving_mask = mask, _moving_mask(moving, mask)
    box = _crop_box(fixed_mask | moving_mask, np.array(fixed.GetSpacing())[::-1],
                    s.crop_margin_mm)
    fixed_c, moving_c = _crop(fixed, box), _crop(moving, box)
    fixed_m = _masked(sitk.Clamp(fixed_c, sitk.sitkFloat32, lo, hi), fixed_mask[box], lo)
    moving_m = _masked(sitk.Clamp(moving_c, sitk.sitkFloat32, lo, hi), moving_mask[box], lo)
    field_img = None if initial is None else _crop(initial.to_sitk(), box)
    levels = list(zip(s.shrink, s.iterations, strict=True))
    if initial is not None and len(levels) > 1:
        levels = levels[1:]  # the initial field already holds the large-scale motion
    for shrink, iters in levels:
        f = _level_grid(fixed_m, shrink, s.min_spacing_mm)
        m = _level_grid(moving_m, shrink, s.min_spacing_mm)  # same grid as f
        init = (sitk.Image(f.GetSize(), sitk.sitkVectorFloat64) if field_img is None else
                sitk.Resample(field_img, f, sitk.Transform(), sitk.sitkLinear, 0.0,
                              sitk.sitkVectorFloat64))
        init.CopyInformation(f)
        demons = sitk.FastSymmetricForcesDemonsRegistrationFilter()
        demons.SetNumberOfIterations(int(iters))
        demons.SetSmoothDisplacementField(True)
        demons.SetStandardDeviations(float(s.smoothing_mm / min(f.GetSpacing())))
        field_img = demons.Execute(f, m, init)
    if field_img.GetSize() != fixed_c.GetSize():
        field_img = sitk.Resample(field_img, fixed_c, sitk.Transform(), sitk.sitkLinear, 0.0,
                                  sitk.sitkVectorFloat64)
    vectors = sitk.GetArrayFromImage(field_img).astype(np.float64)
    pad = [(b.start, n - b.stop) for b, n in zip(box, mask.shape, strict=True)]
    if any(a or b for a, b in pad):  # continue the field outside the box: edge replication
        vectors = np.pad(vectors, [*pad, (0, 0)], mode="edge")
    return DisplacementField(vectors, _grid_of(fixed))


def _crop_box(mask: np.ndarray, spacing_zyx_mm: np.ndarray,
              margin_mm: float | None) -> tuple[slice, slice, slice]:
    """Index box (z, y, x slices) of ``mask``'s voxels widened by ``margin_mm``, within the image;
    the whole image if ``margin_mm`` is None."""
    if margin_mm is None:
        return tuple(slice(0, n) for n in mask.shape)  # type: ignore[return-value]
    out = []
    for axis, n in enumerate(mask.shape):
        hit = np.flatnonzero(mask.any(axis=tuple(a for a in range(3) if a != axis)))
        k = int(np.ceil(margin_mm / spacing_zyx_mm[axis]))
        out.append(slice(max(0, int(hit[0]) - k), min(n, int(hit[-1]) + 1 + k)))
    return tuple(out)  # type: ignore[return-value]


def _crop(img, box: tuple[slice, slice, slice]):  # noqa: ANN001, ANN202
    """The SimpleITK image's sub-image over the (z, y, x) index box, its geometry kept."""
    z, y, x = box
    if all(b.start == 0 and b.stop == n for b, n in zip(box, img.GetSize()[::-1], strict=True)):
        return img
    return img[x.start:x.stop, y.start:y.stop, z.start:z.stop]


def _masked(img, mask: np.ndarray, value: float):  # noqa: ANN001, ANN202
    import SimpleITK as sitk

    arr = sitk.GetArrayFromImage(img)
    out = sitk.GetImageFromArray(np.where(mask, arr, np.float32(value)).astype(np.float32))
    out.CopyInformation(img)
    return out


def _bspline(fixed, moving, mask: np.ndarray, s: RegistrationSettings,  # noqa: ANN001
             given: bool = False) -> DisplacementField:
    import SimpleITK as sitk

    n_levels = len(s.shrink)
    extent = np.array(fixed.GetSize()) * np.array(fixed.GetSpacing())
    coarse = s.grid_spacing_mm * 2 ** (n_levels - 1)
    mesh = [max(1, int(round(e / coarse))) for e in extent]
    tx = sitk.BSplineTransformInitializer(fixed, mesh, order=3)
    reg = sitk.ImageRegistrationMethod()
    reg.SetMetricAsMeanSquares()
    reg.SetMetricFixedMask(_mask_image(mask, fixed))
    reg.SetMetricSamplingStrategy(reg.RANDOM)
    reg.SetMetricSamplingPercentage(BSPLINE_SAMPLING, 1)  # fixed seed: reproducible
    reg.SetInterpolator(sitk.sitkLinear)
    reg.SetOptimizerAsLBFGS2(solutionAccuracy=1e-5, numberOfIterations=int(max(s.iterations)))
    reg.SetInitialTransformAsBSpline(tx, inPlace=True, scaleFactors=[2 ** k for k in range(n_levels)])
    reg.SetShrinkFactorsPerLevel(list(s.shrink))
    reg.SetSmoothingSigmasPerLevel([0.5 * k for k in s.shrink])
    reg.SmoothingSigmasAreSpecifiedInPhysicalUnitsOff()
    reg.Execute(fixed, moving)
    disp = sitk.TransformToDisplacementField(tx, sitk.sitkVectorFloat64, fixed.GetSize(),
                                             fixed.GetOrigin(), fixed.GetSpacing(),
                                             fixed.GetDirection())
    return _field(disp, fixed)


def _grid_of(like):  # noqa: ANN001, ANN202
    from tetdose.core.image import ImageGrid

    return ImageGrid(like.GetOrigin(), like.GetSpacing(), like.GetDirection(), like.GetSize())


def _field(img, like) -> DisplacementField:  # noqa: ANN001
    import SimpleITK as sitk

    return DisplacementField(sitk.GetArrayFromImage(img).astype(np.float64), _grid_of(like))


# --- quality -------------------------------------------------------------------------------------


def _report(fixed, moving, mask: np.ndarray, u: DisplacementField, reference: Image,  # noqa: ANN001
            percent: float, seconds: float) -> RegistrationReport:
    """Metrics, Jacobian and largest |u| over the mask, computed on the mask's bounding box only
    (the same numbers as on the whole image: every quantity is taken over mask voxels)."""
    import SimpleITK as sitk

    box = _crop_box(mask, np.array(fixed.GetSpacing())[::-1], 0.0)
    fixed_b, moving_b, mask_b = _crop(fixed, box), _crop(moving, box), mask[box]
    u_b = _sub_field(u, box)
    f = sitk.GetArrayFromImage(fixed_b).astype(np.float64)
    m0 = sitk.GetArrayFromImage(moving_b).astype(np.float64)
    transform = sitk.DisplacementFieldTransform(sitk.Cast(u_b.to_sitk(), sitk.sitkVectorFloat64))
    m1 = sitk.GetArrayFromImage(sitk.Resample(moving, fixed_b, transform, sitk.sitkLinear,
                                              np.nan)).astype(np.float64)
    seen = mask_b & np.isfinite(m1)  # x + u(x) inside the phase image
    jac = jacobian_range(u, mask)
    norm = np.linalg.norm(u_b.vectors_mm, axis=-1)
    return RegistrationReport(
        percent=float(percent),
        metric_before_hu2=float(np.mean((f - m0)[mask_b] ** 2)),
        metric_after_hu2=float(np.mean((f - m1)[seen] ** 2)) if seen.any() else np.nan,
        jacobian_min=jac.min, jacobian_max=jac.max, folding_fraction=jac.folding_fraction,
        worst_jacobian_mm=jac.worst_mm,
        max_displacement_mm=float(norm[mask_b].max()), seconds=seconds)


def _sub_field(u: DisplacementField, box: tuple[slice, slice, slice]) -> DisplacementField:
    """``u`` on the (z, y, x) index box: the same vectors at the same voxel centres."""
    from tetdose.core.image import ImageGrid

    start = np.array([box[2].start, box[1].start, box[0].start], dtype=float)
    size = (box[2].stop - box[2].start, box[1].stop - box[1].start, box[0].stop - box[0].start)
    grid = ImageGrid(u.grid.index_to_physical(start), u.grid.spacing_mm, u.grid.direction, size)
    return DisplacementField(np.ascontiguousarray(u.vectors_mm[box]), grid)


class JacobianRange(NamedTuple):
    """det(I + ∇u) over a mask: range, fraction of voxels with det ≤ 0, worst voxel's centre [mm]."""

    min: float
    max: float
    folding_fraction: float
    worst_mm: tuple[float, float, float]


def jacobian_range(u: DisplacementField, mask: np.ndarray | None = None) -> JacobianRange:
    """Jacobian determinant of x ↦ x + u(x) (SimpleITK ``DisplacementFieldJacobianDeterminant``,
    central differences in physical units) over ``mask`` (default: every voxel)."""
    import SimpleITK as sitk

    mask = np.ones(u.grid.shape, dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
    # the mask's bounding box and one voxel more (the central differences' neighbours): the same
    # determinants at the mask voxels as on the whole field, at a fraction of the cost
    box = _crop_box(mask, np.ones(3), 1.0)
    sub = _sub_field(u, box)
    det = sitk.GetArrayFromImage(sitk.DisplacementFieldJacobianDeterminant(sub.to_sitk()))
    mask = mask[box]
    d = det[mask]
    worst = np.unravel_index(int(np.argmin(np.where(mask, det, np.inf))), det.shape)
    worst_mm = sub.grid.index_to_physical(np.array(worst[::-1], dtype=float))
    return JacobianRange(float(d.min()), float(d.max()), float(np.mean(d <= 0.0)),
                         (float(worst_mm[0]), float(worst_mm[1]), float(worst_mm[2])))


def _with_inverse_consistency(report: RegistrationReport, u: DisplacementField,
                              w: DisplacementField, mask: np.ndarray,
                              reference: Image) -> RegistrationReport:
    """|u(x) + w(x + u(x))| over the mask voxels whose image x + u(x) lies inside w's grid."""
    from tetdose.errors import GeometryMismatchError

    x = reference.grid.voxel_centers_mm()[mask.ravel()]
    ux = u.vectors_mm.reshape(-1, 3)[mask.ravel()]
    y = x + ux
    idx = w.grid.physical_to_index(y)
    inside = np.all((idx >= 0) & (idx <= np.array(w.grid.size) - 1), axis=1)
    try:
        err = np.linalg.norm(ux[inside] + w.at(y[inside]), axis=1)
    except GeometryMismatchError:  # pragma: no cover - guarded by `inside`
        return report
    return RegistrationReport(**{**asdict(report), "inverse_consistency_mean_mm": float(err.mean()),
                                 "inverse_consistency_max_mm": float(err.max())})


def _identity_report(percent: float) -> RegistrationReport:
    return RegistrationReport(percent=float(percent), metric_before_hu2=0.0, metric_after_hu2=0.0,
                              jacobian_min=1.0, jacobian_max=1.0, folding_fraction=0.0,
                              worst_jacobian_mm=(0.0, 0.0, 0.0), max_displacement_mm=0.0,
                              seconds=0.0, notes=["reference phase: zero field"])
