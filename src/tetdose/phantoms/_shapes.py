"""Implicit shapes, seeded vessel trees and smooth noise for the procedural phantoms.

Every shape is an indicator evaluated on voxel-centre coordinates ``x, y, z`` [mm] (arrays of
one shape, patient LPS frame). Numpy only.
"""

from __future__ import annotations

import math

import numpy as np

#: Random axes tried for a child branch before the branch ends at the organ's surface.
TRIES = 4


def superellipsoid(x: np.ndarray, y: np.ndarray, z: np.ndarray, centre: tuple[float, ...],
                   semi_axes_mm: tuple[float, ...], exponent: float = 2.0) -> np.ndarray:
    """Inside of |dx/a|^e + |dy/b|^e + |dz/c|^e ≤ 1 (e = 2: an ellipsoid)."""
    s = sum(np.abs((q - c) / a) ** exponent for q, c, a in zip((x, y, z), centre, semi_axes_mm,
                                                                strict=True))
    return s <= 1.0


def elliptic_cylinder(x: np.ndarray, y: np.ndarray, z: np.ndarray, a_mm: float, b_mm: float,
                      z_range_mm: tuple[float, float], exponent: float = 2.0) -> np.ndarray:
    """Inside of |x/a|^e + |y/b|^e ≤ 1 with z in ``z_range_mm`` (axis along z through 0)."""
    inside = np.abs(x / a_mm) ** exponent + np.abs(y / b_mm) ** exponent <= 1.0
    return inside & (z >= z_range_mm[0]) & (z <= z_range_mm[1])


def capsule(x: np.ndarray, y: np.ndarray, z: np.ndarray, a: np.ndarray, b: np.ndarray,
            radius_mm: float) -> np.ndarray:
    """Points within ``radius_mm`` of the segment a–b: |p − (a + t(b − a))| ≤ r, t ∈ [0, 1]."""
    d = b - a
    t = ((x - a[0]) * d[0] + (y - a[1]) * d[1] + (z - a[2]) * d[2]) / float(d @ d)
    t = np.clip(t, 0.0, 1.0)
    dist2 = (x - a[0] - t * d[0]) ** 2 + (y - a[1] - t * d[1]) ** 2 + (z - a[2] - t * d[2]) ** 2
    return dist2 <= radius_mm**2


def _rotate(v: np.ndarray, axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues' rotation of ``v`` about the unit ``axis``."""
    c, s = math.cos(angle), math.sin(angle)
    return v * c + np.cross(axis, v) * s + axis * (axis @ v) * (1.0 - c)


def vessel_tree(rng: np.random.Generator, root_mm: np.ndarray, direction: np.ndarray, *,
                length_mm: float, radius_mm: float, depth: int, inside,  # noqa: ANN001
                ratio: float = 0.75, angle_deg: float = 35.0
                ) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """A seeded random binary tree of tube segments (start, end, radius) [mm].

    Each segment ends in two children of ``ratio`` × its length and radius, turned by
    ``angle_deg`` ± 8° to either side about a random axis normal to the parent. A child whose
    end falls outside ``inside(point) -> bool`` is halved; failing that, another random axis is
    drawn, up to ``TRIES`` times, before the branch ends. The root segment is kept as given.
    """
    segments: list[tuple[np.ndarray, np.ndarray, float]] = []
    stack = [(np.asarray(root_mm, float), direction / np.linalg.norm(direction), length_mm,
              radius_mm, depth)]
    while stack:
        start, d, length, radius, level = stack.pop()
        segments.append((start, start + length * d, radius))
        if level == 0:
            continue
        end = start + length * d
        for side in (1.0, -1.0):
            for _ in range(TRIES):
                normal = np.cross(d, rng.standard_normal(3))
                normal /= np.linalg.norm(normal)
                angle = side * math.radians(angle_deg + rng.uniform(-8.0, 8.0))
                child = _rotate(d, normal, angle)
                fits = [f for f in (1.0, 0.5) if inside(end + f * ratio * length * child)]
                if fits:
                    stack.append((end, child, fits[0] * ratio * length, ratio * radius,
                                  level - 1))
                    break
    return segments


def gaussian_filter(field: np.ndarray, sigma_vox: float) -> np.ndarray:
    """Periodic Gaussian blur by FFT: multiply the spectrum by exp(−2π²σ²|f|²)."""
    spectrum = np.fft.rfftn(field)
    freqs = [np.fft.fftfreq(n) for n in field.shape[:-1]] + [np.fft.rfftfreq(field.shape[-1])]
    f2 = sum(np.meshgrid(*(f**2 for f in freqs), indexing="ij", sparse=True))
    return np.fft.irfftn(spectrum * np.exp(-2.0 * math.pi**2 * sigma_vox**2 * f2), field.shape,
                          axes=tuple(range(field.ndim)))


def smooth_noise(rng: np.random.Generator, shape: tuple[int, ...], sigma_vox: float
                 ) -> np.ndarray:
    """Zero-mean, unit-standard-deviation Gaussian random field of correlation length σ."""
    field = gaussian_filter(rng.standard_normal(shape), sigma_vox)
    return (field - field.mean()) / field.std()
