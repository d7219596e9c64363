"""Dose files other codes write, recognised by their name and read as tetdose images or tallies.

=================  ==========================================================================
kind               files
=================  ==========================================================================
``tally``          ``.csv``: per-tet tally (:mod:`tetdose.coupling.tally_csv`)
``3ddose``         ``.3ddose``: EGSnrc dose and relative uncertainty
                   (:mod:`tetdose.coupling.threeddose`)
``rtdose``         ``.dcm`` (or any DICOM file) of Modality RTDOSE: Pixel Data ×
                   DoseGridScaling (PS3.3 C.8.8.3.4) on the Image Plane geometry (SimpleITK)
``image``          NRRD, MetaImage, NIfTI, … (:data:`tetdose.core.io.IMAGE_SUFFIXES`): the
                   voxel values as doses
=================  ==========================================================================

Voxel doses keep the unit of the file; only a ``.3ddose`` carries uncertainties.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from tetdose.core.image import Image
from tetdose.core.io import IMAGE_SUFFIXES, read_image
from tetdose.coupling.threeddose import read_3ddose
from tetdose.errors import DicomError, ImageError, OptionError

KINDS = ("tally", "3ddose", "rtdose", "image")
#: File endings of each kind but rtdose (any DICOM file is one).
SUFFIXES = {"tally": (".csv",), "3ddose": (".3ddose",), "image": IMAGE_SUFFIXES}


def dose_kind(path: str | os.PathLike[str]) -> str:
    """The kind (:data:`KINDS`) of a dose file, by its name or a DICOM preamble."""
    path = Path(path)
    name = path.name.lower()
    for kind, suffixes in SUFFIXES.items():
        if name.endswith(tuple(suffixes)):
            return kind
    if name.endswith(".dcm") or _is_dicom(path):
        return "rtdose"
    raise OptionError(f"{path}: unknown dose format; give a per-tet tally (.csv), an EGSnrc "
                      ".3ddose, a DICOM RT Dose (.dcm) or an image (.nrrd, .mha, .nii.gz …)")


def _is_dicom(path: Path) -> bool:
    try:
        with path.open("rb") as f:
            return f.read(132)[128:] == b"DICM"
    except OSError:
        return False


def read_rt_dose(path: str | os.PathLike[str]) -> Image:
    """The dose of a DICOM RT Dose file [its DoseUnits] on its grid."""
    import pydicom
    import SimpleITK as sitk

    path = Path(path)
    try:
        ds = pydicom.dcmread(path, stop_before_pixels=True)
    except (OSError, pydicom.errors.InvalidDicomError) as exc:
        raise DicomError(f"{path} cannot be read as DICOM ({exc})") from None
    if getattr(ds, "Modality", None) != "RTDOSE" or "DoseGridScaling" not in ds:
        raise DicomError(f"{path} is not an RT Dose (Modality {getattr(ds, 'Modality', '?')}, "
                         "no DoseGridScaling); give the RTDOSE file of the phase")
    try:
        image = Image.from_sitk(sitk.ReadImage(str(path)))
    except RuntimeError as exc:
        raise DicomError(f"cannot read the dose grid of {path}: "
                         f"{str(exc).strip().splitlines()[-1]}") from None
    return image.with_array(image.array.astype(np.float64) * float(ds.DoseGridScaling))


def read_voxel_dose(path: str | os.PathLike[str]) -> tuple[Image, Image | None]:
    """(dose, absolute σ or None) of a voxel dose file (kinds 3ddose, rtdose, image)."""
    kind = dose_kind(path)
    if kind == "3ddose":
        dose, rel = read_3ddose(path)
        return dose, dose.with_array(np.abs(dose.array) * rel.array)
    if kind == "rtdose":
        return read_rt_dose(path), None
    if kind == "image":
        image = read_image(path)
        return image.with_array(np.asarray(image.array, dtype=np.float64)), None
    raise OptionError(f"{path} is a per-tet tally, not a voxel dose")


def check_dose_values(dose: Image, what: str) -> None:
    """Refuse NaN, infinite or negative voxel doses."""
    arr = np.asarray(dose.array, dtype=np.float64)
    if not np.all(np.isfinite(arr)) or np.any(arr < 0):
        raise ImageError(f"{what} holds NaN, infinite or negative doses; give the dose image "
                         "of the run")
