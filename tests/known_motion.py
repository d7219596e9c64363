"""Known motion for registration tests: analytic fields u (reference → phase) and the phase CT.

The phase image is the exact pull-back I_t(y) = I_0(y + v(y)) with v the inverse of u, found at
every voxel centre by the fixed-point iteration v ← −u(y + v) on the *analytic* u (no gridding
error; converges for |∇u| < 1), then trilinear resampling of I_0 (SimpleITK).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import SimpleITK as sitk

from tetdose.core.image import Image

Field = Callable[[np.ndarray], np.ndarray]


def inverse_at(u: Field, y: np.ndarray, iterations: int = 60) -> np.ndarray:
    """v(y) with y + v(y) + u(y + v(y)) = y, i.e. the inverse displacement [mm]."""
    v = np.zeros_like(y)
    for _ in range(iterations):
        v = -u(y + v)
    assert np.abs(v + u(y + v)).max() < 1e-6, "the fixed-point inversion did not converge"
    return v


def warp(image: Image, u: Field, outside_hu: float = -1000.0) -> Image:
    """The phase image of ``image`` under the reference → phase field ``u`` (module docstring)."""
    g = image.grid
    v = inverse_at(u, g.voxel_centers_mm())
    src = image.with_array(np.asarray(image.array, dtype=np.float64)).to_sitk()
    vf = sitk.GetImageFromArray(v.reshape(*g.shape, 3), isVector=True)
    vf.CopyInformation(src)
    tr = sitk.DisplacementFieldTransform(sitk.Cast(vf, sitk.sitkVectorFloat64))
    out = sitk.Resample(src, src, tr, sitk.sitkLinear, outside_hu, sitk.sitkFloat64)
    return Image(sitk.GetArrayFromImage(out), g)


def breathing_field(amplitude_mm: float, diaphragm_z_mm: float, centre_xy_mm: tuple[float, float],
                    width_xy_mm: tuple[float, float], decay_mm: float = 150.0) -> Field:
    """Smooth breathing: the diaphragm moves caudally (−z) by up to ``amplitude_mm``, the motion
    decaying cranially (exp) and laterally (Gaussian), with an anterior (+y) part of 0.3×."""

    def u(p: np.ndarray) -> np.ndarray:
        dz = p[..., 2] - diaphragm_z_mm
        s = np.where(dz >= 0, np.exp(-np.clip(dz, 0, None) / decay_mm), np.exp(-(dz / 60.0) ** 2))
        lat = np.exp(-((p[..., 0] - centre_xy_mm[0]) / width_xy_mm[0]) ** 2
                     - ((p[..., 1] - centre_xy_mm[1]) / width_xy_mm[1]) ** 2)
        out = np.zeros_like(p)
        out[..., 2] = -amplitude_mm * s * lat
        out[..., 1] = 0.3 * amplitude_mm * s * lat
        return out

    return u


def sliding_field(amplitude_mm: float, diaphragm_z_mm: float, centre_xy_mm: tuple[float, float],
                  radii_xy_mm: tuple[float, float], shear_width_mm: float = 5.0,
                  decay_mm: float = 150.0) -> Field:
    """Sliding-like: inside an elliptic cylinder (the lung) cranio-caudal motion as above;
    outside it (the chest wall) none, with a tanh shear layer ``shear_width_mm`` thick."""

    def u(p: np.ndarray) -> np.ndarray:
        dz = p[..., 2] - diaphragm_z_mm
        s = np.where(dz >= 0, np.exp(-np.clip(dz, 0, None) / decay_mm), np.exp(-(dz / 60.0) ** 2))
        r = np.hypot((p[..., 0] - centre_xy_mm[0]) / radii_xy_mm[0],
                     (p[..., 1] - centre_xy_mm[1]) / radii_xy_mm[1])
        inside = 0.5 * (1.0 - np.tanh((r - 1.0) * min(radii_xy_mm) / shear_width_mm))
        out = np.zeros_like(p)
        out[..., 2] = -amplitude_mm * s * inside
        return out

    return u


def displacement_error_mm(got: np.ndarray, u: Field, points_mm: np.ndarray) -> np.ndarray:
    """|u_got − u_true| [mm] at ``points_mm`` (got: displacements at those points)."""
    return np.linalg.norm(got - u(points_mm), axis=-1)
