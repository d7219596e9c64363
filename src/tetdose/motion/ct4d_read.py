"""Read a real 4D-CT: the breathing-phase CT series of a folder, or a list of image files.

A scanner or planning system exports a 4D-CT as one CT series per phase (all files in one
folder, or one sub-folder per phase). DICOM files anywhere below the folder are grouped by
``SeriesInstanceUID`` (headers read with pydicom, ``stop_before_pixels``) and each series is
read with SimpleITK through :func:`tetdose.core.io.read_dicom_files`, which applies the checks of
``read_image`` (modality CT, one slice geometry, uniform slice spacing) and names the series in
its error. The series must share PatientID, FrameOfReferenceUID and StudyInstanceUID
(:func:`tetdose.dicom.identity.check_identities`: a 4D-CT mixing two patients is refused naming
both, unless mismatches are allowed). Phases are ordered by the first of these, in order of
trust, that every series has with distinct values:

1. ``TemporalPositionIndex`` (0020,9128), else ``TemporalPositionIdentifier`` (0020,0100);
2. the phase percentage in ``SeriesDescription`` (``"4D-CT 20%"``, ``"T=20.0 %"``);
3. the earliest ``AcquisitionTime`` (0008,0032) of the series' slices.

The phase percentage [% of the breathing cycle] is the one in ``SeriesDescription`` when every
series has one, else 100·r/K for rank r of K phases. Image files (NRRD, MHA, NIfTI …; a list, or
a folder holding only such files) are ordered by the phase numbers in their names
(``phase_020.0``, ``20%``; 0…K−1 read as indices), else kept in the given (for a folder: name)
order with 100·r/K; names of which only some carry a number, two names of one phase, and a file
given twice are refused.
"""

from __future__ import annotations

import os
import re
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from tetdose.core.image import Image
from tetdose.core.io import read_ct, read_dicom_files
from tetdose.core.phase_names import percents_from_names
from tetdose.dicom.identity import check_identities, identity_of_header
from tetdose.errors import ImageError

#: File name endings read as image files (not DICOM).
IMAGE_SUFFIXES = (".nrrd", ".nhdr", ".mha", ".mhd", ".nii", ".nii.gz")
#: Header fields read per file (everything else is skipped: fast on thousands of slices).
_TAGS = ["SOPClassUID", "Modality", "SeriesInstanceUID", "SeriesDescription", "SeriesNumber",
         "TemporalPositionIndex", "TemporalPositionIdentifier", "AcquisitionTime",
         "ImagePositionPatient", "ImageOrientationPatient", "Rows", "Columns", "PixelSpacing",
         "PatientID", "FrameOfReferenceUID", "StudyInstanceUID"]
_PERCENT = re.compile(r"(\d+(?:\.\d+)?)\s*%")
#: Largest distance [%] between a requested phase and a phase of the 4D-CT.
PERCENT_TOL = 0.5


@dataclass(frozen=True, eq=False)
class Phase4D:
    """One phase of a 4D-CT: ``image`` [HU], its position ``percent`` [% of the cycle], ``source``.

    ``source`` names where it came from (series description and UID, or the file).
    """

    image: Image
    percent: float
    source: str


def read_4dct(path: str | os.PathLike[str] | Sequence[str | os.PathLike[str]]) -> list[Phase4D]:
    """Phases of a 4D-CT folder (DICOM series) or of a list of image files, in phase order.

    See the module docstring for the ordering. ``[p.image for p in phases]`` and
    ``[p.percent for p in phases]`` give the images [HU] and percentages in that order.
    """
    if isinstance(path, str | os.PathLike):
        folder = Path(path)
        if not folder.exists():
            raise ImageError(f"4D-CT {folder} does not exist")
        if not folder.is_dir():
            return _from_files([folder], sort_names=False)
        series, images = _scan(folder)
        if series:
            return _from_series(folder, series)
        if images:
            return _from_files(images, sort_names=True)
        raise ImageError(f"{folder} holds no CT series and no image files ({', '.join(IMAGE_SUFFIXES)});"
                         " give the folder the 4D-CT was exported to")
    files = [Path(p) for p in path]
    if not files:
        raise ImageError("no 4D-CT phases given; pass a folder or one image file per phase")
    return _from_files(files, sort_names=False)


#: What to do when the phases of a mesh series (``dose4d --ct4d``, ``evaluate --4dct``) have no
#: 4D-CT phase at their percentage.
SERIES_FIX = ("the phase meshes must sit at the 4D-CT's phases: deform the mesh with this "
              "4D-CT (`tetdose deform --4dct`) or give `deform --phase-percent` those percentages")


def find_phase(phases: Sequence[Phase4D], percent: float, *,
               fix: str = "pick one of these", what: str = "") -> int:
    """Index of the phase at ``percent`` [%] (within :data:`PERCENT_TOL`); error naming the others
    and ``fix`` (default: pick one, for a percentage the user chose; :data:`SERIES_FIX` for
    phases that come from a mesh series, ``what`` naming them)."""
    got = np.array([p.percent for p in phases])
    k = int(np.argmin(np.abs(got - percent)))
    if abs(got[k] - percent) > PERCENT_TOL:
        raise ImageError(f"the 4D-CT has no {percent:g} % phase{what} (phases: "
                         f"{', '.join(f'{g:g}' for g in got)} %); {fix}")
    return k


# --- DICOM ------------------------------------------------------------------------------------


@dataclass
class _Series:
    uid: str
    files: list[Path]
    headers: list[Any]

    @property
    def description(self) -> str:
        return str(self.headers[0].get("SeriesDescription", "") or "")

    @property
    def label(self) -> str:
        return f"series '{self.description}' ({self.uid})"

    def first(self, keyword: str) -> Any:
        values = [h.get(keyword) for h in self.headers if h.get(keyword) not in (None, "")]
        return values[0] if values else None


def _scan(folder: Path) -> tuple[list[_Series], list[Path]]:
    """CT series (grouped by SeriesInstanceUID) and image files found anywhere below ``folder``."""
    import pydicom
    from pydicom.errors import InvalidDicomError

    groups: dict[str, _Series] = {}
    images = []
    for f in sorted(p for p in folder.rglob("*") if p.is_file()):
        if f.name.lower().endswith(IMAGE_SUFFIXES):
            images.append(f)
            continue
        try:
            h = pydicom.dcmread(f, stop_before_pixels=True, specific_tags=_TAGS)
        except (InvalidDicomError, OSError, ValueError, EOFError):
            continue
        if str(h.get("Modality", "")) != "CT" or "ImagePositionPatient" not in h:
            continue  # RT structures, doses, DICOMDIR, scout views without a position …
        uid = str(h.get("SeriesInstanceUID", ""))
        groups.setdefault(uid, _Series(uid, [], [])).files.append(f)
        groups[uid].headers.append(h)
    return list(groups.values()), images


def _from_series(folder: Path, series: list[_Series]) -> list[Phase4D]:
    check_identities([[identity_of_header(s.headers[0], folder, f"{s.label} in {folder}")
                       for s in series]])  # one patient, one frame, one study (or allowed)
    found = [_PERCENT.search(s.description) is not None for s in series]
    if any(found) and not all(found):
        bare, named = series[found.index(False)], series[found.index(True)]
        raise ImageError(f"{folder}: {bare.label} has no phase percentage in its "
                         f"SeriesDescription while {named.label} has; remove series that are no "
                         "phase (average, MIP) from the folder, or give one image file per phase")
    order, how = _phase_order(folder, series)
    series = [series[i] for i in order]
    percents = _description_percents(series)
    if percents is None:
        percents = [100.0 * r / len(series) for r in range(len(series))]
    elif how != "SeriesDescription" and np.any(np.diff(percents) <= 0):
        warnings.warn(f"{folder}: the phase percentages in SeriesDescription "
                      f"({', '.join(f'{p:g}' for p in percents)} %) do not increase in {how} "
                      f"order; the phases are ordered by {how}", stacklevel=3)
    return [Phase4D(_read_series(s), float(p), s.label)
            for s, p in zip(series, percents, strict=True)]


def _read_series(s: _Series) -> Image:
    """Voxels of one series, slices sorted along the slice normal (checks in read_dicom_files)."""
    iop = np.asarray(s.headers[0].ImageOrientationPatient, dtype=float)
    normal = np.cross(iop[:3], iop[3:])
    pos = [float(np.dot(normal, np.asarray(h.ImagePositionPatient, float))) for h in s.headers]
    idx = np.argsort(pos, kind="stable")
    return read_dicom_files([s.files[i] for i in idx], what=f"{s.label}",
                            headers=[s.headers[i] for i in idx])


def _phase_order(folder: Path, series: list[_Series]) -> tuple[list[int], str]:
    """Series order by the most trusted key that all series have, distinct; else an error."""
    if len(series) == 1:
        return [0], "single series"
    missing = {}
    for keyword in ("TemporalPositionIndex", "TemporalPositionIdentifier"):
        values = [s.first(keyword) for s in series]
        ok = _distinct([None if v is None else float(v) for v in values])
        if ok is not None:
            return ok, keyword
        missing[keyword] = values
    percents = _description_percents(series)
    if percents is not None and (ok := _distinct(percents)) is not None:
        return ok, "SeriesDescription"
    times = [_earliest_time(s) for s in series]
    if (ok := _distinct(times)) is not None:
        return ok, "AcquisitionTime"
    names = ", ".join(s.label for s in series[:3]) + (" …" if len(series) > 3 else "")
    raise ImageError(
        f"{folder}: cannot order its {len(series)} CT series ({names}) by breathing phase: "
        f"{_why('TemporalPositionIndex/TemporalPositionIdentifier', missing['TemporalPositionIndex'])}, "
        f"{_why('a phase percentage (… 20%) in SeriesDescription', percents)}, "
        f"{_why('AcquisitionTime', times)}; give one image file per phase in phase order instead"
    )


def _why(what: str, values: Sequence[Any] | None) -> str:
    if values is None or any(v is None for v in values):
        return f"no {what} in every series"
    return f"{what} not distinct"


def _distinct(values: Sequence[float | None]) -> list[int] | None:
    if any(v is None for v in values) or len(set(values)) != len(values):
        return None
    return sorted(range(len(values)), key=lambda i: values[i])  # type: ignore[arg-type, return-value]


def _description_percents(series: list[_Series]) -> list[float] | None:
    found = [_PERCENT.search(s.description) for s in series]
    return None if any(m is None for m in found) else [float(m.group(1)) for m in found]  # type: ignore[union-attr]


def _earliest_time(s: _Series) -> float | None:
    """Earliest AcquisitionTime of the series' slices [s after midnight], None if absent."""
    seconds = []
    for h in s.headers:
        t = str(h.get("AcquisitionTime", "") or "").strip()
        if len(t) >= 6 and t[:6].isdigit():
            seconds.append(int(t[:2]) * 3600 + int(t[2:4]) * 60 + float(t[4:] or 0))
    return min(seconds) if seconds else None


# --- image files ------------------------------------------------------------------------------


def _from_files(files: list[Path], *, sort_names: bool) -> list[Phase4D]:
    """Phases ordered by the numbers in the names (:func:`~tetdose.core.phase_names.
    percents_from_names`: percentages, or indices 0…K−1), else in the given order at 100·r/K;
    a file given twice, or names of which only some carry a number, are refused."""
    if sort_names:
        files = sorted(files, key=lambda f: f.name)
    seen: dict[Path, Path] = {}
    for f in files:
        if (key := f.resolve()) in seen:
            raise ImageError(f"4D-CT phase file {f} is given twice (also as {seen[key]}); give "
                             "each phase once")
        seen[key] = f
    files, percents = percents_from_names(files, "4D-CT phase files")
    if percents is None:
        percents = [100.0 * r / len(files) for r in range(len(files))]
    return [Phase4D(read_ct(f), float(p), str(f))
            for f, p in zip(files, percents, strict=True)]
