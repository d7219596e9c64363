"""Builders for the DICOM modules shared by the CT Image and RT Dose IODs (PS3.3 Part C).

Patient (C.7.1.1), General Study (C.7.2.1), Frame of Reference (C.7.4.1), General Equipment
(C.7.5.1), Image Plane (C.7.6.2) and SOP Common (C.12.1). Every Type 1 attribute gets a value
and every Type 2 attribute is present (empty when unknown). File writing uses Explicit VR Little
Endian with a conformant File Meta Information header (PS3.10 §7.1).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pydicom
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.errors import InvalidDicomError
from pydicom.uid import ExplicitVRLittleEndian
from pydicom.valuerep import format_number_as_ds

from tetdose._version import __version__
from tetdose.core.image import ImageGrid
from tetdose.dicom.uid import DEFAULT_PREFIX, derive_uid
from tetdose.errors import DicomError

#: Patient and General Study attributes copied from a reference series (Type 2 unless noted).
PATIENT_STUDY_KEYWORDS = (
    "PatientName",
    "PatientID",
    "IssuerOfPatientID",
    "PatientBirthDate",
    "PatientSex",
    "StudyDate",
    "StudyTime",
    "AccessionNumber",
    "ReferringPhysicianName",
    "StudyID",
    "StudyDescription",
)
#: Type 2 attributes of those modules that must be present even when empty.
_TYPE2 = (
    "PatientName",
    "PatientID",
    "PatientBirthDate",
    "PatientSex",
    "StudyDate",
    "StudyTime",
    "AccessionNumber",
    "ReferringPhysicianName",
    "StudyID",
)


@dataclass(frozen=True)
class StudyContext:
    """Who and where: patient/study attributes, Study Instance UID, Frame of Reference UID."""

    attributes: dict[str, object]
    study_instance_uid: str
    frame_of_reference_uid: str
    position_reference_indicator: str = ""
    patient_position: str = ""
    uid_prefix: str | None = DEFAULT_PREFIX

    def apply(self, ds: Dataset) -> None:
        """Set Patient, General Study and Frame of Reference modules on ``ds``."""
        for keyword in _TYPE2:
            setattr(ds, keyword, "")
        for keyword, value in self.attributes.items():
            setattr(ds, keyword, value)
        ds.StudyInstanceUID = self.study_instance_uid
        ds.FrameOfReferenceUID = self.frame_of_reference_uid
        ds.PositionReferenceIndicator = self.position_reference_indicator


def read_reference_header(reference: str | Path) -> Dataset:
    """Header (no pixels) of the first DICOM file of a series folder, or of a single file."""
    path = Path(reference)
    if path.is_dir():
        candidates = sorted(p for p in path.iterdir() if p.is_file())
    elif path.is_file():
        candidates = [path]
    else:
        raise DicomError(f"reference DICOM {path} does not exist; pass a series folder or a file")
    for candidate in candidates:
        try:
            return pydicom.dcmread(candidate, stop_before_pixels=True)
        except (InvalidDicomError, OSError):
            continue
    raise DicomError(f"no DICOM file found in {path}; pass the folder of the reference CT series")


def study_context(
    reference: str | Path | None,
    *,
    seed: str,
    study_instance_uid: str | None = None,
    frame_of_reference_uid: str | None = None,
    uid_prefix: str | None = DEFAULT_PREFIX,
) -> StudyContext:
    """Patient/study context: copied from ``reference`` if given, else anonymous.

    Explicit ``study_instance_uid`` / ``frame_of_reference_uid`` win over the reference. The
    reference's Frame of Reference UID is kept because tetdose images live in the reference CT's
    patient coordinates (a new grid in the same frame, PS3.3 C.7.4.1); pass another UID when the
    image was registered into a different frame. Missing UIDs (anonymised references, or no
    reference) are derived deterministically from ``seed`` (and the reference's identity).
    """
    if reference is None:
        ctx = StudyContext(
            attributes={"PatientName": "Anonymous^", "PatientID": "TETDOSE-ANON", "StudyID": "1"},
            study_instance_uid=derive_uid("study", seed, prefix=uid_prefix),
            frame_of_reference_uid=derive_uid("frame", seed, prefix=uid_prefix),
            uid_prefix=uid_prefix,
        )
    else:
        ctx = _context_from_reference(read_reference_header(reference), uid_prefix)
    if study_instance_uid is not None:
        ctx = replace(ctx, study_instance_uid=str(study_instance_uid))
    if frame_of_reference_uid is not None:
        ctx = replace(ctx, frame_of_reference_uid=str(frame_of_reference_uid))
    return ctx


def _context_from_reference(ref: Dataset, uid_prefix: str | None) -> StudyContext:
    attrs = {k: ref.get(k) for k in PATIENT_STUDY_KEYWORDS if ref.get(k) is not None}
    identity = [str(ref.get(k, "")) for k in ("PatientID", "StudyDate", "StudyTime")]
    study = str(ref.get("StudyInstanceUID", "") or "")
    frame = str(ref.get("FrameOfReferenceUID", "") or "")
    if not study:
        warnings.warn(
            "the reference DICOM has no Study Instance UID (anonymised?); a UID derived from its "
            "Frame of Reference is used, so the new series will not join the original study in a "
            "PACS. Pass study_instance_uid= to set it.",
            stacklevel=4,
        )
        study = derive_uid("study-of-reference", frame, *identity, prefix=uid_prefix)
    if not frame:
        frame = derive_uid("frame-of-reference", study, *identity, prefix=uid_prefix)
    return StudyContext(
        attributes=attrs,
        study_instance_uid=study,
        frame_of_reference_uid=frame,
        position_reference_indicator=str(ref.get("PositionReferenceIndicator", "") or ""),
        patient_position=str(ref.get("PatientPosition", "") or ""),
        uid_prefix=uid_prefix,
    )


def ds_values(values: np.ndarray) -> list[str]:
    """Decimal String values (≤ 16 characters each, PS3.5 §6.2), tiny round-off set to 0."""
    values = np.where(np.abs(values) < 1e-12, 0.0, np.asarray(values, dtype=np.float64))
    return [format_number_as_ds(float(v)) for v in values]


def set_equipment(ds: Dataset) -> None:
    """General Equipment module: Manufacturer (Type 2) plus software version."""
    ds.Manufacturer = "tetdose"
    ds.ManufacturerModelName = "tetdose"
    ds.SoftwareVersions = __version__


def set_image_plane(ds: Dataset, grid: ImageGrid, origin_mm: np.ndarray) -> None:
    """Image Plane module for the plane through ``origin_mm`` of ``grid``.

    Row direction (increasing column index i) is direction[:, 0], column direction is
    direction[:, 1]; Pixel Spacing is [row spacing (y), column spacing (x)] (PS3.3 C.7.6.2.1.1).
    """
    ds.ImageOrientationPatient = ds_values(grid.direction[:, :2].T.ravel())
    ds.ImagePositionPatient = ds_values(origin_mm)
    ds.PixelSpacing = ds_values(grid.spacing_mm[[1, 0]])
    ds.SliceThickness = ds_values(grid.spacing_mm[2:])[0]


def set_pixel_format(ds: Dataset, grid: ImageGrid, bits: int, signed: bool) -> None:
    """Image Pixel module for monochrome integer pixels of ``bits`` bits."""
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME2"
    ds.Rows = grid.size[1]
    ds.Columns = grid.size[0]
    ds.BitsAllocated = bits
    ds.BitsStored = bits
    ds.HighBit = bits - 1
    ds.PixelRepresentation = int(signed)


def save(ds: Dataset, path: Path, sop_class_uid: str, sop_instance_uid: str) -> None:
    """SOP Common module, File Meta header, and write as Explicit VR Little Endian."""
    ds.SpecificCharacterSet = "ISO_IR 192"
    ds.SOPClassUID = sop_class_uid
    ds.SOPInstanceUID = sop_instance_uid
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = sop_class_uid
    meta.MediaStorageSOPInstanceUID = sop_instance_uid
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds.file_meta = meta
    ds.save_as(path, enforce_file_format=True)


def rt_general_plan(ds: Dataset, ctx: StudyContext, label: str, name: str) -> None:
    """RT General Plan (C.8.8.9) and RT Approval (C.8.8.16) attributes of a tetdose plan: dated
    as the study, geometry TREATMENT_DEVICE (PATIENT needs a referenced RT Structure Set),
    UNAPPROVED."""
    ds.RTPlanLabel = label
    ds.RTPlanName = name
    ds.RTPlanDate = ctx.attributes.get("StudyDate", "") or ""
    ds.RTPlanTime = ctx.attributes.get("StudyTime", "") or ""
    ds.RTPlanGeometry = "TREATMENT_DEVICE"
    ds.ApprovalStatus = "UNAPPROVED"
