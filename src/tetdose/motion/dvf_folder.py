"""A folder of registered displacement fields: one per phase of a 4D-CT (reference → phase, mm,
ITK convention, read by ``deform --dvf``) and ``register.json`` beside them (the 4D-CT, the
settings, and per phase: file, percent, source series and the quality report of
:class:`~tetdose.motion.register.RegistrationReport`).

A field that folds (det J ≤ 0 inside the mask) is still written, for inspection; the report says
so and the caller decides (``tetdose register`` exits 2, ``deform --4dct`` stops).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path

import numpy as np

from tetdose.core.image import Image
from tetdose.errors import ImageError
from tetdose.motion.ct4d_read import find_phase, read_4dct
from tetdose.motion.dvf import write_dvf
from tetdose.motion.register import RegistrationReport, RegistrationSettings, register_4dct

#: Name of the registration report written beside the fields.
REPORT_NAME = "register.json"


def field_name(percent: float) -> str:
    """File name of the field of the phase at ``percent`` [%]: ``phase_PPP.P.nrrd``."""
    return f"phase_{percent:05.1f}.nrrd"


def register_to_folder(ct4d: Path | Sequence[Path], reference_percent: float, out_dir: Path, *,
                       mask: Path | None = None,
                       settings: RegistrationSettings | None = None,
                       inverse_consistency: bool = False, progress: bool = True
                       ) -> tuple[list[Path], list[float], list[RegistrationReport]]:
    """Register every phase of the 4D-CT ``ct4d`` (a folder or one image file per phase,
    :func:`~tetdose.motion.ct4d_read.read_4dct`) to its phase at ``reference_percent``, inside
    ``mask`` (a label image's non-zero voxels; default the body), and write the fields and
    :data:`REPORT_NAME` into ``out_dir``. Returns (field files, phase percents, reports)."""
    settings = settings or RegistrationSettings()
    phases = read_4dct(ct4d)
    ref = find_phase(phases, reference_percent)
    mask_arr = None if mask is None else mask_on(mask, phases[ref].image)
    percents = [p.percent for p in phases]
    results = register_4dct([p.image for p in phases], ref, percents=percents, mask=mask_arr,
                            settings=settings, inverse_consistency=inverse_consistency,
                            progress=progress)
    out_dir.mkdir(parents=True, exist_ok=True)
    names = [field_name(p) for p in percents]
    for name, (field, _) in zip(names, results, strict=True):
        write_dvf(out_dir / name, field)
    reports = [r for _, r in results]
    sources = [str(ct4d)] if isinstance(ct4d, str | Path) else [str(p) for p in ct4d]
    doc = {"reference_percent": percents[ref], "ct4d": sources, "settings": asdict(settings),
           "phases": [{"file": n, "source": p.source, **r.as_dict()}
                      for n, p, r in zip(names, phases, reports, strict=True)]}
    (out_dir / REPORT_NAME).write_text(json.dumps(doc, indent=2))
    return [out_dir / n for n in names], percents, reports


def percents_of(dvf_files: Sequence[Path]) -> list[float] | None:
    """Phase percentages of fields written by :func:`register_to_folder` (from its report), or
    None when the files are not all from one such folder."""
    folders = {Path(f).parent for f in dvf_files}
    if len(folders) != 1 or not (report := next(iter(folders)) / REPORT_NAME).exists():
        return None
    by_name = {p["file"]: p["percent"] for p in json.loads(report.read_text())["phases"]}
    if not all(Path(f).name in by_name for f in dvf_files):
        return None
    return [float(by_name[Path(f).name]) for f in dvf_files]


def mask_on(path: Path, like: Image) -> np.ndarray:
    """Non-zero voxels of the label image at ``path``, resampled onto ``like``'s grid (nearest,
    by physical coordinates), as a boolean (nz, ny, nx) array."""
    import SimpleITK as sitk

    from tetdose.core.io import read_labels

    m = read_labels(path, f"the mask {path}")
    arr = m.array if m.grid.same_as(like.grid) else sitk.GetArrayFromImage(sitk.Resample(
        m.to_sitk(), like.to_sitk(), sitk.Transform(), sitk.sitkNearestNeighbor, 0))
    if not np.any(arr):
        raise ImageError(f"the mask {path} holds no non-zero voxel on the reference phase's grid")
    return np.asarray(arr) != 0
