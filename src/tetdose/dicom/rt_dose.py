"""Write a dose image [Gy] as a DICOM RT Dose (PS3.3 A.18) on the CT's frame of reference.

One multi-frame instance: Patient, General Study, RT Series, Frame of Reference, General
Equipment, General Image, Image Plane, Image Pixel, Multi-frame, RT Dose and SOP Common modules.
Pixels are unsigned integers of 16 or 32 bits with dose = stored · DoseGridScaling (PS3.3
C.8.8.3.4); the round-trip error is at most DoseGridScaling / 2. (dicom3tools 2022's dciodvfy
aborts on 32-bit Pixel Data, so only 16-bit files can be checked with it.) GridFrameOffsetVector holds the
offsets of the frames from the first along the image normal, starting at 0 (C.8.8.3.2), and
FrameIncrementPointer points to it. A left-handed grid is written as its right-handed equivalent
(frames reversed) so that the offsets increase, which readers such as GDCM/SimpleITK and
plastimatch require. SimpleITK returns the stored integers (it does not apply DoseGridScaling,
tag 3004|000e): multiply by it. 16-bit doses are read by every planning system; 32 bits give
~2·10⁻¹⁰ relative resolution but a few older systems only accept 16.

DoseSummationType PLAN requires a Referenced RT Plan Sequence (C.8.8.3). A dose computed by
tetdose comes from a ``plan.toml``, not from a DICOM plan, so unless the caller names an existing
plan's SOP Instance UID, a minimal RT Plan (A.20: RT General Plan with RTPlanGeometry
TREATMENT_DEVICE and approval UNAPPROVED, no beams) is written beside the dose
(``<name>.rtplan.dcm``) and referenced, so the pair is self-consistent in any archive. Given the
plan's linac beams, that RT Plan holds them (beams, control points, fraction scheme:
:mod:`tetdose.plan.rt_plan`).
"""

from __future__ import annotations

import warnings
from contextlib import ExitStack
from pathlib import Path
from typing import Protocol

import numpy as np
from pydicom.dataset import Dataset
from pydicom.tag import Tag
from pydicom.uid import RTDoseStorage, RTPlanStorage
from pydicom.valuerep import format_number_as_ds

from tetdose._atomic import atomic_write_file
from tetdose.core.image import Image, ImageGrid
from tetdose.dicom.modules import (
    StudyContext,
    ds_values,
    rt_general_plan,
    save,
    set_equipment,
    set_image_plane,
    set_pixel_format,
    study_context,
)
from tetdose.dicom.uid import DEFAULT_PREFIX, derive_uid, image_digest
from tetdose.errors import DicomError


class Plan(Protocol):
    """What an RT Dose needs of a plan (:class:`tetdose.plan.model.Plan` is one): its linac beams
    and their RT Plan dataset (the DICOM layer sits below the plan, so it asks, not imports)."""

    treatment_beams: tuple[object, ...]

    def rt_plan_dataset(self, ctx: StudyContext, plan_uid: str, number: int) -> Dataset: ...

#: Summation types written; others need fraction/beam references tetdose does not have.
SUMMATION_TYPES = ("PLAN",)
#: DoseUnits (PS3.3 C.8.8.3: GY or RELATIVE) by the dose's unit: an unprescribed Monte Carlo dose
#: is in Gy per source photon, which is not an absolute dose, so it is written as RELATIVE.
DOSE_UNITS = {"Gy": "GY", "Gy per fraction": "GY", "Gy per source photon": "RELATIVE",
              "Gy per source particle": "RELATIVE"}


def rt_plan_path(dose_path: str | Path) -> Path:
    """Where :func:`write_rt_dose` puts the minimal RT Plan it references: ``<name>.rtplan.dcm``."""
    dose_path = Path(dose_path)
    return dose_path.with_name(dose_path.name.removesuffix(".dcm") + ".rtplan.dcm")


def write_rt_dose(
    dose_gy: Image,
    path: str | Path,
    *,
    reference_ct: str | Path | None = None,
    frame_of_reference_uid: str | None = None,
    study_instance_uid: str | None = None,
    summation_type: str = "PLAN",
    referenced_rt_plan_uid: str | None = None,
    bits: int = 16,
    series_number: int = 2000,
    series_description: str = "tetdose Monte Carlo dose",
    uid_prefix: str | None = DEFAULT_PREFIX,
    plan: Plan | None = None,
    unit: str = "Gy",
    dose_to: str = "medium",
) -> Path:
    """Write ``dose_gy`` [Gy] as an RT Dose file at ``path`` (atomically); return ``path``.

    ``dose_to``: "medium" or "water" (dose to medium or to water, :mod:`tetdose.dose.dose_to`),
    stated in DoseComment and the series description (DICOM has no attribute for it).

    ``unit``: what the values are, a key of :data:`DOSE_UNITS`. "Gy per source photon" (an
    unprescribed dose) and "Gy per source particle" (another code's, imported) are written with
    DoseUnits RELATIVE, and DoseComment and the series description say so; "Gy" and "Gy per
    fraction" with DoseUnits GY.

    ``plan``: with linac beams, the RT Plan written beside the dose holds them
    (:mod:`tetdose.plan.rt_plan`) instead of the beamless placeholder.

    ``reference_ct``: the CT series folder whose patient, study and Frame of Reference UID the
    dose shares (or pass ``frame_of_reference_uid``/``study_instance_uid``). Without
    ``referenced_rt_plan_uid`` a minimal RT Plan is also written, at :func:`rt_plan_path`.
    """
    dose_gy = _checked_dose(dose_gy)
    if summation_type not in SUMMATION_TYPES:
        raise DicomError(f"DoseSummationType {summation_type!r} is not supported; use 'PLAN'")
    if bits not in (16, 32):
        raise DicomError(f"bits must be 16 or 32, got {bits}")
    if unit not in DOSE_UNITS:
        raise DicomError(f"dose unit {unit!r} is unknown; use one of {sorted(DOSE_UNITS)}")
    if dose_to not in ("medium", "water"):
        raise DicomError(f"dose_to {dose_to!r} is unknown; use 'medium' or 'water'")
    if DOSE_UNITS[unit] == "RELATIVE":
        series_description = f"{series_description} ({unit})"
    series_description = f"{series_description}, dose to {dose_to}"
    if reference_ct is None and frame_of_reference_uid is None:
        warnings.warn(
            "no reference_ct or frame_of_reference_uid: the RT Dose gets a new Frame of "
            "Reference and cannot be overlaid on the CT; give the CT's DICOM series folder "
            "(export-dose --like, or reference_ct=)",
            stacklevel=2,
        )
    digest = image_digest(dose_gy)
    ctx = study_context(
        reference_ct,
        seed=digest,
        study_instance_uid=study_instance_uid,
        frame_of_reference_uid=frame_of_reference_uid,
        uid_prefix=uid_prefix,
    )
    series_uid = derive_uid(
        "rtdose-series", digest, ctx.study_instance_uid, ctx.frame_of_reference_uid, bits,
        series_number, series_description, referenced_rt_plan_uid, prefix=uid_prefix,
    )  # fmt: skip
    path = Path(path)
    with ExitStack() as stack:
        plan_uid = referenced_rt_plan_uid
        if plan_uid is None:
            plan_uid = derive_uid(series_uid, "plan", prefix=uid_prefix)
            plan_tmp = stack.enter_context(atomic_write_file(rt_plan_path(path)))
            if plan is not None and plan.treatment_beams:
                save(plan.rt_plan_dataset(ctx, plan_uid, series_number + 1), plan_tmp,
                     RTPlanStorage, plan_uid)
            else:
                _write_plan_stub(plan_tmp, ctx, plan_uid, series_number + 1)
        dose_tmp = stack.enter_context(atomic_write_file(path))
        ds = _dose_dataset(dose_gy, ctx, series_uid, series_number, series_description, bits)
        ds.DoseUnits = DOSE_UNITS[unit]
        ds.DoseComment = f"dose to {dose_to} in {unit}"
        ds.DoseSummationType = summation_type
        ref = Dataset()
        ref.ReferencedSOPClassUID = RTPlanStorage
        ref.ReferencedSOPInstanceUID = plan_uid
        ds.ReferencedRTPlanSequence = [ref]
        save(ds, dose_tmp, RTDoseStorage, derive_uid(series_uid, "instance", prefix=uid_prefix))
    return path


def _checked_dose(dose: object) -> Image:
    if not isinstance(dose, Image):
        raise DicomError(f"dose_gy must be a tetdose.core.image.Image, got {type(dose).__name__}")
    arr = dose.array
    if arr.ndim != 3 or not np.issubdtype(arr.dtype, np.number) or np.iscomplexobj(arr):
        raise DicomError(f"dose_gy must be a real 3-D image, got {arr.dtype} {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise DicomError("dose_gy holds NaN or infinite values; replace them before writing")
    if arr.shape[0] < 2:
        raise DicomError(
            "dose_gy has a single slice; an RT Dose needs at least 2 frames (GridFrameOffsetVector "
            "has multiplicity 2-n): compute the dose on a grid with 2 or more slices"
        )
    if arr.min() < 0:
        raise DicomError(
            f"dose_gy has negative values (min {arr.min():g} Gy); RT Dose stores unsigned "
            "doses: clip statistical noise below 0 before writing"
        )
    return dose


def right_handed(image: Image) -> Image:
    """The same voxels on a grid with det(direction) = +1 (frames reversed if needed)."""
    grid = image.grid
    if np.linalg.det(grid.direction) > 0:
        return image
    direction = grid.direction.copy()
    direction[:, 2] *= -1.0
    origin = grid.origin_mm + grid.direction[:, 2] * (grid.size[2] - 1) * grid.spacing_mm[2]
    return Image(image.array[::-1], ImageGrid(origin, grid.spacing_mm, direction, grid.size))


def dose_to_stored(dose_gy: np.ndarray, bits: int) -> tuple[np.ndarray, str]:
    """Dose [Gy] → (unsigned stored values, DoseGridScaling as a DS string ≤ 16 chars)."""
    top = 2**bits - 1
    peak = float(dose_gy.max())
    scaling = format_number_as_ds(peak / top * (1 + 1e-9)) if peak > 0 else "1"
    stored = np.clip(np.rint(dose_gy / float(scaling)), 0, top)
    return stored.astype(f"<u{bits // 8}"), scaling


def _dose_dataset(
    dose: Image, ctx: StudyContext, series_uid: str, number: int, description: str, bits: int
) -> Dataset:
    dose = right_handed(dose)
    grid = dose.grid
    stored, scaling = dose_to_stored(np.asarray(dose.array, dtype=np.float64), bits)
    ds = _series_base(ctx, "RTDOSE", series_uid, number, description)
    ds.InstanceNumber = 1  # General Image
    ds.ContentDate = ctx.attributes.get("StudyDate", "") or ""
    ds.ContentTime = ctx.attributes.get("StudyTime", "") or ""
    set_image_plane(ds, grid, grid.origin_mm)
    set_pixel_format(ds, grid, bits, signed=False)
    ds.NumberOfFrames = grid.size[2]  # Multi-frame
    ds.FrameIncrementPointer = Tag(0x3004, 0x000C)
    ds.DoseType = "PHYSICAL"
    ds.GridFrameOffsetVector = ds_values(np.arange(grid.size[2]) * grid.spacing_mm[2])
    ds.DoseGridScaling = scaling
    ds.TissueHeterogeneityCorrection = ["IMAGE"]
    ds.PixelData = stored.tobytes()
    return ds


def _series_base(
    ctx: StudyContext, modality: str, series_uid: str, number: int, description: str
) -> Dataset:
    """Patient, General Study, Frame of Reference, RT Series and General Equipment modules."""
    ds = Dataset()
    ctx.apply(ds)
    ds.Modality = modality
    ds.SeriesInstanceUID = series_uid
    ds.SeriesNumber = int(number)
    ds.SeriesDescription = description
    ds.OperatorsName = ""
    set_equipment(ds)
    return ds


def _write_plan_stub(path: Path, ctx: StudyContext, plan_uid: str, number: int) -> None:
    """Minimal RT Plan IOD (A.20): RT General Plan + RT Approval, no beams."""
    series_uid = derive_uid(plan_uid, "plan-series", prefix=ctx.uid_prefix)
    ds = _series_base(ctx, "RTPLAN", series_uid, number, "tetdose plan placeholder")
    ds.InstanceNumber = 1
    rt_general_plan(ds, ctx, "tetdose MC", "tetdose Monte Carlo")
    ds.RTPlanDescription = "placeholder for a plan.toml dose calculation; not deliverable"
    save(ds, path, RTPlanStorage, plan_uid)
