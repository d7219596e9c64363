"""One patient, one frame: the DICOM inputs of one command must belong together.

Every DICOM input (a file, or every DICOM file below a folder) is read header-only and grouped by
series. Its **identity** is PatientID (0010,0020), FrameOfReferenceUID (0020,0052) — for an RT
Structure Set, which has no Frame of Reference module, the FrameOfReferenceUID of its
ReferencedFrameOfReferenceSequence (3006,0010) — and StudyInstanceUID (0020,000D).

:func:`check_identities` compares them across all inputs of a command (CT, the phases of a 4D-CT,
RT Structure Set, RT Plan, RT Dose):

- PatientID: every input that states one must state the same (an RT Plan of another patient
  would be dosed on this CT);
- FrameOfReferenceUID: likewise (coordinates of two frames share no origin: a structure or an
  isocentre of another frame lands in the wrong place);
- StudyInstanceUID: the phases of one 4D-CT (the CT series of one input folder) must share it
  (phases from two studies are two acquisitions, not one breathing cycle).

An empty or absent value is not compared. A mismatch raises
:class:`~tetdose.errors.GeometryMismatchError` naming both values and inputs, unless mismatches
are allowed (the CLI's ``--allow-frame-mismatch``, or :func:`frame_policy` / ``allow=True``): then
it warns once and the message is recorded in every JSON record the command writes
(:func:`tetdose._atomic.record_note`, key :data:`NOTE_KEY`).
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from tetdose._atomic import record_note, recorded_notes
from tetdose.errors import GeometryMismatchError

#: Header fields read per file (pixels and everything else are skipped).
TAGS = ["Modality", "PatientID", "FrameOfReferenceUID", "StudyInstanceUID", "SeriesInstanceUID",
        "SeriesDescription", "ReferencedFrameOfReferenceSequence"]
#: Key of the allowed mismatches in the JSON records.
NOTE_KEY = "input_mismatch_allowed"
#: How the refusal names the way to allow a mismatch.
ALLOW_HINT = ("pass --allow-frame-mismatch (Python: tetdose.dicom.identity.frame_policy(True)) "
              "if you know they belong together")
#: Modality → the name the messages use.
_KINDS = {"CT": "CT", "RTSTRUCT": "RT Structure Set", "RTPLAN": "RT Plan", "RTDOSE": "RT Dose",
          "MR": "MR", "PT": "PET", "REG": "registration", "SEG": "segmentation"}


@dataclass(frozen=True)
class Identity:
    """Who and where one DICOM series (or single-file object) belongs: ``what`` names it."""

    what: str
    modality: str
    patient_id: str
    frame_uid: str
    study_uid: str
    series_uid: str


@dataclass
class _FramePolicy:
    allow: bool = False
    reported: set[str] = field(default_factory=set)


_POLICY: ContextVar[_FramePolicy | None] = ContextVar("tetdose_frame_policy", default=None)


@contextmanager
def frame_policy(allow: bool) -> Iterator[None]:
    """During the block, :func:`check_identities` without an explicit ``allow`` allows (warns
    about) mismatched patients, frames and studies instead of refusing them."""
    token = _POLICY.set(_FramePolicy(bool(allow)))
    try:
        yield
    finally:
        _POLICY.reset(token)


def _kind(modality: str) -> str:
    return _KINDS.get(modality, modality or "DICOM object")


def _value(ds: Any, keyword: str) -> str:  # noqa: ANN401 - pydicom Dataset
    return str(ds.get(keyword, "") or "").strip()


def identity_of_header(ds: Any, path: str | os.PathLike[str],  # noqa: ANN401
                       what: str | None = None) -> Identity:
    """The :class:`Identity` of one pydicom header read from ``path`` (``what``: its name in
    messages, default from its modality, series description and ``path``)."""
    modality = _value(ds, "Modality")
    frame = _value(ds, "FrameOfReferenceUID")
    if not frame:
        refs = ds.get("ReferencedFrameOfReferenceSequence") or []
        frames = {_value(item, "FrameOfReferenceUID") for item in refs} - {""}
        frame = frames.pop() if len(frames) == 1 else ""
    description = _value(ds, "SeriesDescription")
    named = f" '{description}'" if description else ""
    return Identity(what or f"the {_kind(modality)}{named} {path}", modality,
                    _value(ds, "PatientID"),
                    frame, _value(ds, "StudyInstanceUID"), _value(ds, "SeriesInstanceUID"))


def _header(path: Path) -> Any | None:  # noqa: ANN401 - pydicom Dataset or None
    import pydicom
    from pydicom.errors import InvalidDicomError

    try:
        return pydicom.dcmread(path, stop_before_pixels=True, specific_tags=TAGS)
    except (InvalidDicomError, OSError, ValueError, EOFError, TypeError, AttributeError):
        return None


def identities_of(path: str | os.PathLike[str]) -> list[Identity]:
    """Identities of a DICOM file, or of every series in a folder — the folder's own files, or
    if it has no DICOM file, those below it (a 4D-CT with one sub-folder per phase) — (empty:
    no DICOM)."""
    path = Path(path)
    if path.is_file():
        ds = _header(path)
        return [] if ds is None else [identity_of_header(ds, path)]
    if not path.is_dir():
        return []
    found = _series_in(path, sorted(p for p in path.iterdir() if p.is_file()))
    return found or _series_in(path, sorted(p for p in path.rglob("*") if p.is_file()))


def _series_in(path: Path, files: list[Path]) -> list[Identity]:
    series: dict[tuple[str, str], Identity] = {}
    for f in files:
        ds = _header(f)
        if ds is None:
            continue
        ident = identity_of_header(ds, path)
        key = (ident.series_uid or str(f), ident.modality)
        if key not in series:
            series[key] = ident
    return list(series.values())


def check_identities(groups: Sequence[Sequence[Identity]], *, allow: bool | None = None
                     ) -> list[str]:
    """Refuse (or with ``allow`` warn about and record) mismatches among ``groups``.

    Each group is the identities of one input; PatientID and FrameOfReferenceUID are compared
    across all of them, StudyInstanceUID among the CT series of one group (a 4D-CT). ``allow``
    defaults to :func:`frame_policy` (False outside it). Returns the mismatch messages allowed.
    """
    policy = _POLICY.get()
    allowed = (policy.allow if policy is not None else False) if allow is None else allow
    found = []
    flat = [i for g in groups for i in g]
    for keyword, attr in (("PatientID", "patient_id"), ("FrameOfReferenceUID", "frame_uid")):
        found += _differences(flat, keyword, attr)
    for g in groups:
        found += _differences([i for i in g if i.modality == "CT"], "StudyInstanceUID",
                              "study_uid", " (the phases of one 4D-CT come from one study)")
    if not found:
        return []
    if not allowed:
        raise GeometryMismatchError(f"{found[0]}; combine inputs of one patient and one frame of "
                                    f"reference, or {ALLOW_HINT}")
    for message in found:
        text = f"{message}; allowed (--allow-frame-mismatch), the inputs are combined as they are"
        if policy is None or message not in policy.reported:
            warnings.warn(text, stacklevel=2)
        if policy is not None:
            policy.reported.add(message)
    notes = recorded_notes().get(NOTE_KEY, [])
    record_note(NOTE_KEY, [*notes, *(m for m in found if m not in notes)])
    return found


def _differences(idents: Iterable[Identity], keyword: str, attr: str, why: str = ""
                 ) -> list[str]:
    """One message per value differing from the first stated value of ``attr``."""
    first: Identity | None = None
    out = []
    for ident in idents:
        value = getattr(ident, attr)
        if not value:
            continue
        if first is None:
            first = ident
        elif value != getattr(first, attr):
            out.append(f"{keyword} differs: {getattr(first, attr)!r} in {first.what}, "
                       f"{value!r} in {ident.what}{why}")
    return out


def check_inputs(paths: Iterable[str | os.PathLike[str]], *, allow: bool | None = None
                 ) -> list[str]:
    """:func:`check_identities` of the DICOM files and folders among ``paths`` (others are
    skipped)."""
    groups = [g for g in (identities_of(p) for p in paths) if g]
    return check_identities(groups, allow=allow) if groups else []
