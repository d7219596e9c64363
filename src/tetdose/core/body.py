"""The patient's body in a CT: the largest connected region above an HU threshold."""

from __future__ import annotations

import numpy as np

from tetdose.errors import ImageError


def largest_component(above: np.ndarray, what: str) -> np.ndarray:
    """The largest 6-connected component of the boolean array ``above`` (same shape).

    ``what`` names the threshold in the error raised when nothing is above it.
    """
    from scipy import ndimage

    labels, n = ndimage.label(above)
    if n == 0:
        raise ImageError(f"no CT voxel is above {what}: the image holds no body; is it a CT "
                         "in HU? (or give a mask)")
    sizes = np.bincount(labels.ravel())
    sizes[0] = 0
    return labels == int(np.argmax(sizes))
