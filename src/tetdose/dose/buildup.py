"""Which cells lie in the build-up region, where the scored kerma exceeds the absorbed dose.

tetdose deposits electron energy where the photon interacted (kerma). Shallower than the
build-up depth d_max (:func:`tetdose.plan.spectra.build_up_depth_mm`) there is no
charged-particle equilibrium and the true dose is lower, down to 15–50 % of the maximum at the
skin. This module marks those cells so that plots and DVHs can flag them: a voxel is in the
build-up region when its centre is closer than d_max to the body outline, the body being the
voxels denser than ``body_g_cm3`` (Euclidean distance transform, scipy.ndimage, in mm with the
grid spacing). This is the depth along the surface normal; oblique beams have a somewhat larger
build-up region along their axis, so it marks a lower bound.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from tetdose.core.image import Image

#: Density above which a voxel belongs to the body [g/cm³] (lung ≥ 0.2, air ≈ 0.001).
BODY_G_CM3 = 0.1


def build_up_mask(density: Image, d_max_mm: float, *, body_g_cm3: float = BODY_G_CM3
                  ) -> np.ndarray:
    """Boolean array (numpy shape of the grid): body voxels within ``d_max_mm`` of the skin."""
    body = np.asarray(density.array) > body_g_cm3
    # Distance from each body voxel centre to the nearest outside voxel centre, minus half a
    # voxel: the outline lies between the two centres.
    spacing = density.grid.spacing_mm[::-1]  # numpy axes (k, j, i)
    padded = np.pad(body, 1, constant_values=False)  # the grid's border is outside the body
    dist = ndimage.distance_transform_edt(padded, sampling=spacing)[1:-1, 1:-1, 1:-1]
    return body & (dist - 0.5 * float(spacing.min()) < d_max_mm)


def build_up_fraction(mask: np.ndarray, structure: np.ndarray, weight: np.ndarray | None = None
                      ) -> float:
    """Fraction (by ``weight``, default voxel count) of a structure's voxels in the build-up."""
    w = np.ones(mask.shape) if weight is None else np.asarray(weight)
    s = np.asarray(structure, dtype=bool)
    total = float(w[s].sum())
    return float(w[s & mask].sum() / total) if total > 0 else 0.0
