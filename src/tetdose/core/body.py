"""The patient's body in a CT: the largest connected region above an HU threshold; the
near-maximum dose in tissue (D0.1cm³ over the cells above a density floor)."""

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


#: Tissue: density at least this [g/cm³] (≈ −950 HU on Schneider et al.'s calibration). Inflated
#: lung (−850 HU ≈ 0.16 g/cm³) is tissue; air (−1000 HU ≈ 0.001 g/cm³), the airways' air and
#: the noise of near-empty voxels are not. (0.2 g/cm³ would drop much of the lung, the organ
#: tetdose's breathing studies are about.)
TISSUE_FLOOR_G_CM3 = 0.05
#: The near-maximum every output reports: the minimum dose of the hottest this many cm³.
NEAR_MAX_CM3 = 0.1
#: What the ``near_max…`` entries of the run records and summaries are.
NEAR_MAX_SAID = (f"D{NEAR_MAX_CM3:g}cm³: the lowest dose of the hottest {NEAR_MAX_CM3:g} cm³ of "
                 f"the cells with density ≥ {TISSUE_FLOOR_G_CM3:g} g/cm³ (tissue, never air)")


def near_max_gy(dose_gy: np.ndarray, volume_cm3: np.ndarray | float,
                density_g_cm3: np.ndarray | None = None, *,
                floor_g_cm3: float = TISSUE_FLOOR_G_CM3, near_cm3: float = NEAR_MAX_CM3) -> float:
    """D0.1cm³ in tissue [Gy]: the smallest dose of the hottest ``near_cm3`` of the elements
    (voxels or tets, ``volume_cm3`` each) whose density is at least ``floor_g_cm3`` (all, without
    densities). A Monte Carlo dose's single hottest cell is noise, and in a CT it is often an air
    voxel (few interactions in little mass); a near-maximum over tissue is what a physicist reads
    (ICRU Report 83 §3.2 reports D2 % as near-maximum; D0.1cm³ is the small-volume form). When
    the tissue holds less than ``near_cm3``, its maximum; NaN without tissue."""
    d = np.asarray(dose_gy, dtype=np.float64).ravel()
    v = np.broadcast_to(np.asarray(volume_cm3, dtype=np.float64), np.shape(dose_gy)).ravel()
    keep = v > 0
    if density_g_cm3 is not None:
        keep &= np.asarray(density_g_cm3, dtype=np.float64).ravel() >= floor_g_cm3
    if not keep.any():
        return float("nan")
    d, v = d[keep], v[keep]
    order = np.argsort(-d, kind="stable")
    hottest = np.cumsum(v[order])
    i = int(np.searchsorted(hottest, near_cm3 * (1.0 - 1e-12)))
    return float(d[order][min(i, len(d) - 1)])
