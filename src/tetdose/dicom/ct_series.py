"""Write an HU image as a DICOM CT Image Storage series, and a 4D-CT as one series per phase.

Each slice k of the image (numpy ``array[k]``, rows = y, columns = x) is one CT Image IOD
instance (PS3.3 A.3): Patient, General Study, General Series, Frame of Reference, General
Equipment, General Image, Image Plane, Image Pixel, CT Image, VOI LUT and SOP Common modules.
Geometry follows the image's grid exactly, for any orthonormal direction D:
ImagePositionPatient_k = origin + D[:, 2] · k · Δz, ImageOrientationPatient = (D[:, 0], D[:, 1]),
PixelSpacing = [Δy, Δx]. Pixels are int16 with RescaleSlope 1 and an integer RescaleIntercept
chosen so the rounded HU fit (stored = round(HU) − intercept), so HU are kept to ±0.5.
A left-handed grid (det D = −1, e.g. a y-flipped one) is written slice by slice as it is; readers
that sort slices along ImageOrientation's normal (GDCM, SimpleITK) then return the equivalent
right-handed grid (same voxels in space, slice order reversed).
"""

from __future__ import annotations

import hashlib
import re
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np
from pydicom.dataset import Dataset
from pydicom.uid import CTImageStorage
from tqdm import tqdm

from tetdose._atomic import atomic_write_dir
from tetdose.core.image import Image, ImageGrid
from tetdose.dicom.modules import (
    StudyContext,
    ds_values,
    save,
    set_equipment,
    set_image_plane,
    set_pixel_format,
    study_context,
)
from tetdose.dicom.uid import DEFAULT_PREFIX, derive_uid, image_digest
from tetdose.errors import DicomError

_INT16 = np.iinfo(np.int16)
#: File names of slices and phase folders, as written here.
_SLICE_NAME = re.compile(r"CT\d{5}\.dcm")
_PHASE_NAME = re.compile(r"phase_\d{3}(\.\d)?")
#: Default display windows (centre, width) [HU]: soft tissue and lung.
WINDOWS_HU = ((40.0, 400.0), (-600.0, 1500.0))


def hu_to_stored(hu: np.ndarray) -> tuple[np.ndarray, int]:
    """Rounded HU → (int16 stored values, RescaleIntercept) with HU = stored + intercept.

    The intercept is 0 when the HU fit int16, else the minimum HU + 32768; values still above
    the int16 range are clipped with a warning.
    """
    hu = np.asarray(hu)
    lo, hi = float(np.rint(hu.min())), float(np.rint(hu.max()))  # rint is monotone
    intercept = 0 if (lo >= _INT16.min and hi <= _INT16.max) else int(lo) - _INT16.min
    if hi - intercept > _INT16.max:
        warnings.warn(
            f"HU range {lo:g}…{hi:g} is wider than 16 bits; values above "
            f"{intercept + _INT16.max} HU are clipped",
            stacklevel=3,
        )
    stored = np.empty(hu.shape, dtype="<i2")
    rows, out = hu.reshape(len(hu), -1), stored.reshape(len(hu), -1)
    for k in range(len(hu)):  # slice by slice: cache-friendly, no full-size temporaries
        rounded = np.rint(rows[k] - intercept if intercept else rows[k])
        if hi - intercept > _INT16.max:
            np.clip(rounded, _INT16.min, _INT16.max, out=rounded)
        out[k] = rounded
    return stored, intercept


def _check_image(image: object, what: str) -> Image:
    if not isinstance(image, Image):
        raise DicomError(f"{what} must be a tetdose.core.image.Image, got {type(image).__name__}")
    if image.array.ndim != 3:
        raise DicomError(f"{what} must be 3-D, got an array of shape {image.array.shape}")
    if not np.issubdtype(image.array.dtype, np.number) or np.iscomplexobj(image.array):
        raise DicomError(f"{what} must hold real numbers, got dtype {image.array.dtype}")
    if not np.all(np.isfinite(image.array)):
        raise DicomError(f"{what} holds NaN or infinite values; replace them before writing")
    return image


def write_ct_series(
    image_hu: Image,
    out_dir: str | Path,
    *,
    reference: str | Path | None = None,
    series_number: int = 1000,
    series_description: str = "tetdose virtual CT",
    temporal_position: int | None = None,
    n_temporal_positions: int | None = None,
    study_instance_uid: str | None = None,
    frame_of_reference_uid: str | None = None,
    uid_prefix: str | None = DEFAULT_PREFIX,
    overwrite: bool = True,
    progress: bool | None = False,
) -> list[Path]:
    """Write ``image_hu`` [HU] as one CT series in ``out_dir`` (atomically); return the files.

    ``reference``: a DICOM CT series folder (or file) whose patient, study and frame of
    reference the new series joins; without it anonymous but valid ones are written. UIDs are
    derived from the voxel values, grid and these parameters (see :mod:`tetdose.dicom.uid`), so
    a rerun writes identical bytes. ``out_dir`` is replaced as a whole (``overwrite``) or not at
    all; a non-empty folder holding other files than a previous series is refused
    (:class:`~tetdose.errors.OutputError`) unless the CLI's ``--overwrite`` is in force.
    ``progress``: tqdm bar (None: only on a terminal).
    """
    image_hu = _check_image(image_hu, "image_hu")
    _check_target(out_dir, overwrite)
    pixels = _Pixels.of(image_hu)
    ctx = study_context(
        reference,
        seed=pixels.digest,
        study_instance_uid=study_instance_uid,
        frame_of_reference_uid=frame_of_reference_uid,
        uid_prefix=uid_prefix,
    )
    with atomic_write_dir(out_dir, overwrite=overwrite, marker=False, owned=_is_series) as tmp:
        names = _write_series(
            pixels, tmp, ctx, series_number, series_description, temporal_position,
            n_temporal_positions, progress,
        )  # fmt: skip
    return [Path(out_dir) / n for n in names]


def write_ct_series_4d(
    images_hu: Sequence[Image],
    out_dir: str | Path,
    *,
    phase_percent: Sequence[float],
    reference: str | Path | None = None,
    series_number: int = 1000,
    study_instance_uid: str | None = None,
    frame_of_reference_uid: str | None = None,
    uid_prefix: str | None = DEFAULT_PREFIX,
    overwrite: bool = True,
    progress: bool | None = False,
) -> list[Path]:
    """Write a 4D-CT: one series per breathing phase in ``out_dir/phase_PPP/``; return folders.

    All series share the Study Instance UID and Frame of Reference UID and have unique Series
    Instance UIDs, SeriesDescription "4D-CT <p>%", SeriesNumber ``series_number + index``,
    TemporalPositionIdentifier = index + 1 and NumberOfTemporalPositions = number of phases.
    The whole ``out_dir`` is written atomically (all phases or none).
    """
    images = [_check_image(im, f"images_hu[{i}]") for i, im in enumerate(images_hu)]
    percents = [float(p) for p in phase_percent]
    if not images or len(percents) != len(images):
        raise DicomError(
            f"need one phase_percent per image, got {len(percents)} for {len(images)} images"
        )
    folders = [_phase_folder(p) for p in percents]
    if len(set(folders)) != len(folders):
        raise DicomError(f"phase percentages {percents} are not distinct; give each phase its own")
    _check_target(out_dir, overwrite)
    pixels = [_Pixels.of(im) for im in images]
    seed = hashlib.sha256("".join([p.digest for p in pixels] + [repr(percents)]).encode())
    ctx = study_context(
        reference,
        seed=seed.hexdigest(),
        study_instance_uid=study_instance_uid,
        frame_of_reference_uid=frame_of_reference_uid,
        uid_prefix=uid_prefix,
    )
    with atomic_write_dir(out_dir, overwrite=overwrite, marker=False, owned=_is_series_4d) as tmp:
        for i, (pix, pct, folder) in enumerate(zip(pixels, percents, folders, strict=True)):
            (tmp / folder).mkdir()
            _write_series(
                pix, tmp / folder, ctx, series_number + i, f"4D-CT {pct:g}%", i + 1, len(images),
                progress,
            )  # fmt: skip
    return [Path(out_dir) / f for f in folders]


def _check_target(out_dir: str | Path, overwrite: bool) -> None:
    if Path(out_dir).exists() and not overwrite:
        raise DicomError(f"{out_dir} exists; remove it or pass overwrite=True to replace it")


def _is_series(folder: Path) -> bool:
    """True if ``folder`` holds only slice files as :func:`write_ct_series` names them, so it
    may be replaced (a DICOM folder carries no marker file: DICOM tools read every file)."""
    return all(p.is_file() and _SLICE_NAME.fullmatch(p.name) for p in folder.iterdir())


def _is_series_4d(folder: Path) -> bool:
    """True if ``folder`` holds only phase folders of slice files (a previous 4D-CT)."""
    return all(p.is_dir() and _PHASE_NAME.fullmatch(p.name) and _is_series(p)
               for p in folder.iterdir())


def _phase_folder(percent: float) -> str:
    if not 0.0 <= percent < 100.0:
        raise DicomError(f"breathing phase {percent}% is outside [0, 100)")
    return f"phase_{percent:03.0f}" if percent == round(percent) else f"phase_{percent:05.1f}"


class _Pixels(NamedTuple):
    """int16 pixels of a whole series (one RescaleIntercept) and a digest of what is written."""

    stored: Image
    intercept: int
    digest: str

    @staticmethod
    def of(image: Image) -> _Pixels:
        stored, intercept = hu_to_stored(image.array)
        stored_image = image.with_array(stored)
        return _Pixels(stored_image, intercept, image_digest(stored_image, intercept))


def _write_series(
    pixels: _Pixels,
    folder: Path,
    ctx: StudyContext,
    series_number: int,
    description: str,
    temporal_position: int | None,
    n_temporal: int | None,
    progress: bool | None,
) -> list[str]:
    """Write every slice of ``pixels`` into ``folder``; return the file names."""
    series_uid = derive_uid(
        "ct-series", pixels.digest, ctx.study_instance_uid, ctx.frame_of_reference_uid,
        series_number, description, temporal_position, n_temporal, prefix=ctx.uid_prefix,
    )  # fmt: skip
    grid = pixels.stored.grid
    ds = _series_dataset(grid, ctx, series_uid, series_number, description, pixels.intercept)
    if temporal_position is not None:
        ds.TemporalPositionIdentifier = int(temporal_position)
        ds.NumberOfTemporalPositions = int(n_temporal or temporal_position)
    normal = np.cross(grid.direction[:, 0], grid.direction[:, 1])
    names = []
    for k in tqdm(range(grid.size[2]), desc=description, unit="slice", disable=_disable(progress)):
        position = grid.origin_mm + grid.direction[:, 2] * (k * grid.spacing_mm[2])
        set_image_plane(ds, grid, position)
        ds.SliceLocation = ds_values(np.array([position @ normal]))[0]
        ds.InstanceNumber = k + 1
        ds.PixelData = pixels.stored.array[k].tobytes()
        name = f"CT{k + 1:05d}.dcm"
        sop_uid = derive_uid(series_uid, "slice", k, prefix=ctx.uid_prefix)
        save(ds, folder / name, CTImageStorage, sop_uid)
        names.append(name)
    return names


def _disable(progress: bool | None) -> bool | None:
    return None if progress is None else not progress


def _series_dataset(
    grid: ImageGrid,
    ctx: StudyContext,
    series_uid: str,
    series_number: int,
    description: str,
    intercept: int,
) -> Dataset:
    """All attributes common to the slices of one series."""
    ds = Dataset()
    ctx.apply(ds)
    ds.Modality = "CT"  # General Series
    ds.SeriesInstanceUID = series_uid
    ds.SeriesNumber = int(series_number)
    ds.SeriesDescription = description
    ds.PatientPosition = ctx.patient_position
    ds.Laterality = ""
    set_equipment(ds)
    ds.ImageType = ["DERIVED", "SECONDARY", "AXIAL"]  # General Image / CT Image
    ds.ContentDate = ctx.attributes.get("StudyDate", "") or ""
    ds.ContentTime = ctx.attributes.get("StudyTime", "") or ""
    ds.DerivationDescription = "virtual CT written by tetdose"
    ds.SpacingBetweenSlices = ds_values(grid.spacing_mm[2:])[0]
    set_pixel_format(ds, grid, 16, signed=True)
    ds.RescaleIntercept = str(intercept)  # CT Image
    ds.RescaleSlope = "1"
    ds.RescaleType = "HU"
    ds.KVP = ""
    ds.AcquisitionNumber = ""
    ds.WindowCenter = [f"{c:g}" for c, _ in WINDOWS_HU]  # VOI LUT
    ds.WindowWidth = [f"{w:g}" for _, w in WINDOWS_HU]
    ds.WindowCenterWidthExplanation = ["SOFT_TISSUE", "LUNG"]
    return ds
