"""Boundary checks shared by every command, so the same bad value is refused the same way."""

from __future__ import annotations

import warnings

import numpy as np

from tetdose.errors import DensityError


def check_density(density_g_cm3: np.ndarray, *, what: str, fix: str,
                  negative: str = "error") -> np.ndarray:
    """Refuse NaN or infinite densities [g/cm³]; refuse (``negative="error"``), warn about
    (``"warn"``) or allow (``"allow"``) negative ones. Returns the values as float64.

    The message names how many values are bad, the first ids and ``fix``.
    """
    rho = np.asarray(density_g_cm3, dtype=np.float64)
    bad = ~np.isfinite(rho)
    if bad.any():
        ids = np.flatnonzero(bad.ravel())
        raise DensityError(f"{ids.size} of {rho.size} {what} are NaN or infinite (first ids "
                           f"{ids[:5].tolist()}); {fix}")
    neg = rho < 0
    if negative != "allow" and neg.any():
        ids = np.flatnonzero(neg.ravel())
        msg = (f"{ids.size} of {rho.size} {what} are negative (min {rho.min():.4g} g/cm³, first "
               f"ids {ids[:5].tolist()}); {fix}")
        if negative == "error":
            raise DensityError(msg)
        warnings.warn(msg, stacklevel=3)
    return rho
