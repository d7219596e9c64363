"""Mesher inputs as one label image: a label map, RT Structure Set ROIs, a body outline.

* A label image (NRRD / MHA / NIfTI / DICOM SEG that SimpleITK reads) is used as it is.
* RT Structure Set ROIs are rasterized on the CT grid by
  :func:`tetdose.dicom.rtstruct.structure_mask`; ROI i (in the order asked) becomes label
  i + 1, later ROIs winning where they overlap. An ROI is asked for by its name, or — when two
  ROIs share one name — as ``NAME (NUMBER)`` with its ROI number; the bare shared name is
  refused, listing both.
* ``body="auto"`` adds the CT's patient outline (:func:`tetdose.meshing.labels.body_mask`),
  resampled by nearest neighbour onto the label grid when it differs from the CT grid, as label
  ``max + 1`` under every other label (refused when the outline misses the label image's grid
  or holds none of its labels); ``body=N`` only makes sure label N is meshed (refused when the
  image has no label N).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from tetdose.core.image import Image
from tetdose.errors import ImageError
from tetdose.meshing.labels import as_label_array, body_mask


def labels_from_structures(path: str, ct: Image, rois: Sequence[str]) -> tuple[Image, dict[int, str]]:
    """Label image on the CT grid from the ROIs ``rois`` of the RT Structure Set ``path``."""
    from tetdose.dicom.rtstruct import read_rtstruct, structure_mask

    if not rois:
        raise ImageError("name the ROIs to mesh with --roi NAME (repeat for several)")
    chosen = select_rois(read_rtstruct(path), rois, str(path))
    out = np.zeros(ct.grid.shape, dtype=np.int32)
    names = {}
    for i, (name, structure) in enumerate(zip(rois, chosen, strict=True)):
        out[structure_mask(structure, ct.grid)] = i + 1
        names[i + 1] = name
    return Image(out, ct.grid), names


def select_rois(structures: Sequence[Any], rois: Sequence[str], what: str) -> list[Any]:
    """The structures asked for by name, or by ``NAME (NUMBER)`` where names repeat (module
    docstring); an ambiguous or unknown name is an :class:`ImageError` listing the choices."""
    by_name: dict[str, list[Any]] = {}
    for s in structures:
        by_name.setdefault(s.name, []).append(s)
    by_key = {f"{s.name} ({s.number})": s for s in structures}
    out = []
    for roi in rois:
        same = by_name.get(roi, [])
        if len(same) == 1:
            out.append(same[0])
        elif len(same) > 1:
            keys = " or ".join(f"--roi '{roi} ({s.number})'" for s in same)
            raise ImageError(f"{what} holds {len(same)} ROIs named {roi!r} (ROI numbers "
                             f"{', '.join(str(s.number) for s in same)}); say which: {keys}")
        elif roi in by_key:
            out.append(by_key[roi])
        else:
            raise ImageError(f"{what} has no ROI named {roi!r}; it holds "
                             f"{sorted({s.name for s in structures})}")
    return out


def _on_grid(mask: np.ndarray, source: Image, target: Image) -> np.ndarray:
    """A boolean mask of ``source``'s grid resampled (nearest voxel) onto ``target``'s grid."""
    if source.grid.same_as(target.grid):
        return mask
    import SimpleITK as sitk

    moving = source.with_array(mask.astype(np.uint8)).to_sitk()
    resampled = sitk.Resample(moving, target.to_sitk(), sitk.Transform(), sitk.sitkNearestNeighbor,
                              0, sitk.sitkUInt8)
    return sitk.GetArrayFromImage(resampled).astype(bool)


def with_body(labels: Image, ct: Image, body_label: int | None = None) -> tuple[Image, int]:
    """``labels`` with the CT's body outline added as ``body_label`` (default max + 1) where
    no other label is; returns the image and the body label."""
    arr = as_label_array(labels.array).astype(np.int32)
    body = _on_grid(body_mask(ct.array), ct, labels)
    if not body.any():
        raise ImageError("the CT's body outline does not overlap the label image's grid (no "
                         "voxel of it lies there): give the CT the labels were drawn on (same "
                         "patient frame), or --body N naming the body's label")
    if not (body & (arr != 0)).any():
        raise ImageError("the CT's body outline holds none of the labels: the CT and the label "
                         "image do not overlap; give the CT the labels were drawn on")
    lab = int(arr.max()) + 1 if body_label is None else int(body_label)
    out = arr.copy()
    out[body & (arr == 0)] = lab
    return Image(out, labels.grid), lab
