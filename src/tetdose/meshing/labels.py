"""Label images as mesher input: checks (a CT is not a label map), default sizes, body outline.

Default target edge of a label (volume V, largest inscribed half-thickness r):

    h = clip(min(d_eq / 8, 2 r), 1.5 · min spacing, ``MAX_DEFAULT_SIZE_MM``),  d_eq = (6V/π)^⅓,

so a 2.5 cm tumour gets about 3 mm, a lung (2 L) 12 mm, and a layer two voxels thick about its
thickness. The body outline of a CT (``--body auto``) is the largest connected component of
HU > ``BODY_THRESHOLD_HU``, with its holes filled slice by slice (the lungs and airways are
holes of the body in every axial slice) and then in 3-D.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping

import numpy as np
from scipy import ndimage

from tetdose._typing import FloatArray, IntArray
from tetdose.core.body import largest_component
from tetdose.core.image import Image, ImageGrid
from tetdose.core.io import check_labels
from tetdose.errors import ImageError

#: More distinct values than this, or any negative value: the image is a CT, not labels.
MAX_LABELS = 1000
#: Largest default target edge [mm].
MAX_DEFAULT_SIZE_MM = 12.0
#: Body outline threshold [HU] (between air −1000 and fat −100).
BODY_THRESHOLD_HU = -500.0


def as_label_array(arr: np.ndarray, what: str = "the label image") -> np.ndarray:
    """``arr`` as an integer label array; a CT (negative values, thousands of distinct values) is
    refused with an :class:`ImageError` saying what to pass instead, and non-integer values by
    the one rule of label images (:func:`tetdose.core.io.check_labels`: resample with nearest
    neighbour)."""
    arr = np.asarray(arr)
    hint = ("it looks like a CT, not a label map; pass the CT with --ct and a segmentation "
            "with --labels (or --structures)")
    if arr.dtype.kind in "iuf" and arr.size and np.nanmin(arr) < 0:
        raise ImageError(f"{what} has negative values (min {np.nanmin(arr):g}): {hint}")
    if arr.dtype.kind not in "iubf":
        raise ImageError(f"{what} has dtype {arr.dtype}; give an integer label image")
    if arr.dtype.kind == "f":
        arr = check_labels(Image(arr, _unit_grid(arr.shape)), what).array
    step = max(1, arr.size // 2_000_000)  # a strided sample decides fast for a big CT
    if len(np.unique(arr.ravel()[::step])) > MAX_LABELS or len(np.unique(arr)) > MAX_LABELS:
        raise ImageError(f"{what} has more than {MAX_LABELS} distinct values: {hint}")
    return arr


def _unit_grid(shape: tuple[int, ...]) -> ImageGrid:
    return ImageGrid(np.zeros(3), np.ones(3), np.eye(3), tuple(reversed(shape)))


def checked_label_ids(arr: np.ndarray, label_ids: Iterable[int] | None) -> IntArray:
    """The sorted labels to mesh, each present in ``arr`` (default: every non-zero label)."""
    arr = as_label_array(arr)
    present = np.unique(arr)
    ids = present[present != 0] if label_ids is None else np.unique(np.asarray(list(label_ids)))
    if ids.size == 0:
        raise ImageError("the label image has no non-zero label; nothing to mesh")
    if np.any(ids <= 0):
        raise ImageError(f"labels to mesh must be positive, got {ids.tolist()}")
    missing = np.setdiff1d(ids, present)
    if missing.size:
        raise ImageError(f"no voxel carries label {', '.join(map(str, missing.tolist()))}; the "
                         f"image has labels {present[present != 0].tolist()[:40]}")
    return ids.astype(np.int64)


def default_sizes_mm(volumes_mm3: Mapping[int, float], depths_mm: Mapping[int, float],
                     spacing_mm: FloatArray) -> dict[int, float]:
    """Default target edge [mm] per label (module docstring) from its volume and half-thickness."""
    lo = 1.5 * float(np.min(spacing_mm))
    out = {}
    for lab, vol in volumes_mm3.items():
        d_eq = (6.0 * vol / math.pi) ** (1.0 / 3.0)
        h = min(d_eq / 8.0, 2.0 * depths_mm[lab])
        out[int(lab)] = float(np.clip(h, lo, max(lo, MAX_DEFAULT_SIZE_MM)))
    return out


def body_mask(ct_hu: np.ndarray, threshold_hu: float = BODY_THRESHOLD_HU) -> np.ndarray:
    """Patient outline: largest 6-connected component of HU > threshold, holes filled."""
    body = largest_component(np.asarray(ct_hu) > threshold_hu, f"{threshold_hu:g} HU")
    for k in range(body.shape[0]):
        body[k] = ndimage.binary_fill_holes(body[k])
    return ndimage.binary_fill_holes(body)


def relabelled(arr: np.ndarray, masks: Mapping[int, np.ndarray], body: np.ndarray | None = None,
               body_label: int | None = None) -> np.ndarray:
    """A label array: ``body_label`` on ``body``, then each mask's label (later masks win)."""
    out = np.zeros(arr.shape, dtype=np.int32)
    if body is not None and body_label is not None:
        out[body] = body_label
    for lab, mask in masks.items():
        out[mask] = lab
    return out
