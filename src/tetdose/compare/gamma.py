"""Gamma index (Low et al., Med. Phys. 25 (1998) 656) on a regular grid, global or local.

For a reference point r with dose D_r(r), the gamma value is

    γ(r) = min_o sqrt( |o|² / Δd²  +  (D_e(r + o) − D_r(r))² / ΔD(r)² ),

Δd the distance to agreement [mm], ΔD = dose_percent % of the normalization dose (global: the
reference maximum unless given) or of D_r(r) itself (local). D_e between voxel centres is the
trilinear interpolant of the evaluated dose, so the search is sub-voxel (Wendling et al.,
Med. Phys. 34 (2007) 1647: search on a fine interpolated grid in order of increasing distance).

Search: offsets o lie on a lattice aligned with the voxels, of step ≤ Δd / ``interp_fraction``
per axis (the voxel centres belong to it, so a shift by whole voxels is found exactly), inside
the sphere |o| ≤ ``max_gamma``·Δd. They are visited in shells of increasing distance; a point
leaves the search as soon as its best γ² so far is ≤ (distance of the next shell)²/Δd² + L²,
since no farther offset can lower it; L = dist(D_r, [min, max] of D_e over the searched box)/ΔD
bounds the dose term (so flat regions with a dose offset end at once). Points whose γ exceeds
``max_gamma`` get γ = inf ("> max_gamma").

Only reference points with D_r ≥ ``threshold_percent`` % of the normalization dose (and inside
``mask``) are evaluated — where dose matters. Work is ∝ (evaluated points) × (offsets visited);
``max_points`` evaluates a seeded uniform random sample of them instead, and the pass rate then
carries its binomial standard error sqrt(p(1−p)/n).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tetdose._typing import BoolArray, FloatArray, IntArray
from tetdose.core.image import Image
from tetdose.errors import DoseError, OptionError

#: Reference points handled per chunk (bounds the memory of the search).
POINT_CHUNK = 1_000_000


@dataclass(frozen=True, eq=False)
class GammaResult:
    """Gamma values (NaN where not evaluated, inf where > ``max_gamma``) and the criteria."""

    gamma: FloatArray
    dose_percent: float
    dta_mm: float
    local: bool
    threshold_percent: float
    normalization_gy: float
    max_gamma: float
    sampled: bool

    @property
    def evaluated(self) -> BoolArray:
        return ~np.isnan(self.gamma)

    @property
    def n_evaluated(self) -> int:
        return int(self.evaluated.sum())

    @property
    def pass_rate_percent(self) -> float:
        """100 · (points with γ ≤ 1) / (points evaluated)."""
        n = self.n_evaluated
        return 100.0 * float((self.gamma[self.evaluated] <= 1.0).sum()) / n if n else float("nan")

    @property
    def pass_rate_std_percent(self) -> float:
        """Binomial standard error of the pass rate when points were sampled, else 0."""
        if not self.sampled or self.n_evaluated == 0:
            return 0.0
        p = self.pass_rate_percent / 100.0
        return 100.0 * float(np.sqrt(p * (1.0 - p) / self.n_evaluated))

    def summary(self) -> dict[str, float | bool | str]:
        kind = "local" if self.local else "global"
        return {"criterion": f"{self.dose_percent:g}%/{self.dta_mm:g}mm {kind}",
                "threshold_percent": self.threshold_percent,
                "normalization_gy": self.normalization_gy, "n_evaluated": self.n_evaluated,
                "pass_rate_percent": self.pass_rate_percent,
                "pass_rate_std_percent": self.pass_rate_std_percent, "sampled": self.sampled,
                "max_gamma": self.max_gamma}


def gamma_index(reference: Image, evaluated: Image, *, dose_percent: float = 3.0,
                dta_mm: float = 3.0, local: bool = False, threshold_percent: float = 10.0,
                normalization_gy: float | None = None, max_gamma: float = 2.0,
                interp_fraction: int = 10, mask: BoolArray | None = None,
                max_points: int | None = None, seed: int = 0) -> GammaResult:
    """Gamma of ``evaluated`` against ``reference`` (same grid; doses in Gy), module docstring.

    ``mask`` (numpy shape of the dose) restricts the reference points further, e.g. to one slice.
    A threshold outside [0, 100) %, a reference dose that is zero (or NaN) everywhere, and a
    selection holding no point are errors, so a pass rate is never NaN.
    """
    reference.grid.require_same(evaluated.grid, "the reference and evaluated doses")
    _check_criteria(dose_percent, dta_mm, max_gamma, interp_fraction, threshold_percent)
    ref = np.asarray(reference.array, dtype=np.float64)
    ev_arr = np.asarray(evaluated.array, dtype=np.float64)
    for name, arr in (("reference", ref), ("evaluated", ev_arr)):
        if not np.all(np.isfinite(arr)):
            raise DoseError(f"the {name} dose holds {int((~np.isfinite(arr)).sum())} NaN or "
                            "infinite voxels; recompute it")
    norm = float(ref.max()) if normalization_gy is None else float(normalization_gy)
    if not norm > 0:
        raise DoseError(f"the normalization dose is {norm:g} Gy: the reference dose is zero "
                        "everywhere (did the beam miss?); nothing to compare")
    select = ref >= threshold_percent / 100.0 * norm
    if mask is not None:
        select &= np.asarray(mask, dtype=bool).reshape(ref.shape)
    points = np.flatnonzero(select)
    if len(points) == 0:
        raise DoseError(f"no reference point reaches the threshold of {threshold_percent:g} % of "
                        f"{norm:.4g} Gy (inside the mask); lower the threshold")
    sampled = max_points is not None and len(points) > max_points
    if sampled:
        rng = np.random.default_rng(seed)
        points = np.sort(rng.choice(points, size=int(max_points), replace=False))
    offsets = _Offsets(reference.grid.spacing_mm, dta_mm, interp_fraction, max_gamma)
    padded, strides = offsets.pad(ev_arr)
    ev_lo, ev_hi, corner = offsets.local_range(ev_arr, np.unravel_index(points, ref.shape))
    gamma2 = np.empty(len(points))
    for lo in range(0, len(points), POINT_CHUNK):
        chunk = points[lo:lo + POINT_CHUNK]
        k, j, i = np.unravel_index(chunk, ref.shape)
        p = offsets.pad_width
        base = (k + p[2]) * strides[2] + (j + p[1]) * strides[1] + (i + p[0])
        ref_val = ref.ravel()[chunk]
        dd = dose_percent / 100.0 * (ref_val if local else np.full_like(ref_val, norm))
        inv_dd2 = 1.0 / np.maximum(dd, np.finfo(float).tiny) ** 2
        at = (k - corner[0], j - corner[1], i - corner[2])
        gap = np.maximum(np.maximum(ev_lo[at] - ref_val, ref_val - ev_hi[at]), 0.0)
        lb2 = gap**2 * inv_dd2 * (1.0 - 1e-9)
        gamma2[lo:lo + len(chunk)] = offsets.search(padded, strides, base, ref_val, inv_dd2, lb2)
    gamma = np.full(ref.size, np.nan)
    g = np.sqrt(gamma2)
    gamma[points] = np.where(g <= max_gamma, g, np.inf)
    return GammaResult(gamma.reshape(ref.shape), float(dose_percent), float(dta_mm), bool(local),
                       float(threshold_percent), norm, float(max_gamma), bool(sampled))


def _check_criteria(dose_percent: float, dta_mm: float, max_gamma: float, interp_fraction: int,
                    threshold_percent: float) -> None:
    for name, value in (("dose_percent", dose_percent), ("dta_mm", dta_mm),
                        ("max_gamma", max_gamma)):
        if not (np.isfinite(value) and value > 0):
            raise OptionError(f"gamma {name} must be a finite number > 0, got {value}")
    if not interp_fraction >= 1:
        raise OptionError(f"gamma interp_fraction must be ≥ 1, got {interp_fraction}")
    if not 0.0 <= threshold_percent < 100.0:
        raise OptionError(f"the gamma threshold must lie in [0, 100) % of the normalization "
                          f"dose (CLI: --threshold), got {threshold_percent:g}")


class _Offsets:
    """Search offsets on a voxel-aligned lattice, sorted by distance and cut into shells."""

    def __init__(self, spacing_mm: FloatArray, dta_mm: float, interp_fraction: int,
                 max_gamma: float) -> None:
        self.dta_mm = dta_mm
        step_target = dta_mm / interp_fraction
        n_sub = np.maximum(np.ceil(spacing_mm / step_target - 1e-9).astype(np.int64), 1)
        step = spacing_mm / n_sub
        radius = max_gamma * dta_mm
        m_max = np.floor(radius / step + 1e-9).astype(np.int64)
        axes = [np.arange(-m, m + 1) for m in m_max]
        m = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        dist = np.sqrt(((m * step) ** 2).sum(axis=1))
        keep = dist <= radius * (1 + 1e-12)
        order = np.argsort(dist[keep], kind="stable")
        m, self.dist_mm = m[keep][order], dist[keep][order]
        self.whole = m // n_sub  # integer voxel shift (floor)
        self.frac = (m - self.whole * n_sub) / n_sub  # in [0, 1)
        self.pad_width = np.abs(self.whole).max(axis=0) + 1
        width = float(step.min())
        shell = np.floor(self.dist_mm / width + 1e-9).astype(np.int64)
        self.shell_start = np.r_[np.flatnonzero(np.r_[True, shell[1:] != shell[:-1]]), len(m)]

    def pad(self, evaluated: FloatArray) -> tuple[FloatArray, IntArray]:
        """Evaluated dose padded with NaN (no bounds checks), flat; strides (1, NX, NX·NY)."""
        p = self.pad_width
        out = np.pad(evaluated, ((p[2], p[2]), (p[1], p[1]), (p[0], p[0])),
                     constant_values=np.nan)
        nz, ny, nx = out.shape
        return out.ravel(), np.array([1, nx, nx * ny], dtype=np.int64)

    def local_range(self, evaluated: FloatArray, kji: tuple[IntArray, ...]
                    ) -> tuple[FloatArray, FloatArray, tuple[int, int, int]]:
        """Min and max of the evaluated dose over the box holding every searched cell corner,
        on the block spanning the points ``kji`` (plus the search margin), and its corner."""
        from scipy.ndimage import maximum_filter, minimum_filter

        w = self.pad_width[::-1]
        if len(kji[0]) == 0:
            return np.zeros((1, 1, 1)), np.zeros((1, 1, 1)), (0, 0, 0)
        lo = [max(int(a.min()) - int(m), 0) for a, m in zip(kji, w, strict=True)]
        hi = [int(a.max()) + int(m) + 1 for a, m in zip(kji, w, strict=True)]
        block = evaluated[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
        size = tuple(int(2 * m + 1) for m in w)
        return (minimum_filter(block, size=size, mode="nearest"),
                maximum_filter(block, size=size, mode="nearest"), (lo[0], lo[1], lo[2]))

    def search(self, ev: FloatArray, strides: IntArray, base: IntArray, ref_val: FloatArray,
               inv_dd2: FloatArray, lb2: FloatArray) -> FloatArray:
        """min over offsets of |o|²/Δd² + (D_e(r+o) − D_r)² / ΔD², with early exit per point.

        ``lb2`` bounds the dose term from below for every offset (the evaluated dose stays within
        its local min/max), so a point is final once γ² ≤ |o_next|²/Δd² + lb2.
        """
        g2 = np.full(len(base), np.inf)
        inv_dta2 = 1.0 / self.dta_mm**2
        shift = self.whole @ strides
        for s in range(len(self.shell_start) - 1):
            a, b = self.shell_start[s], self.shell_start[s + 1]
            active = np.flatnonzero(g2 > self.dist_mm[a] ** 2 * inv_dta2 + lb2)
            if len(active) == 0:
                break
            pts, rv, idd, g = base[active], ref_val[active], inv_dd2[active], g2[active]
            for o in range(a, b):
                value = _trilinear(ev, pts + shift[o], self.frac[o], strides)
                cand = self.dist_mm[o] ** 2 * inv_dta2 + (value - rv) ** 2 * idd
                np.fmin(g, cand, out=g)
            g2[active] = g
        return g2


def _trilinear(ev: FloatArray, at: IntArray, frac: FloatArray, strides: IntArray) -> FloatArray:
    """Trilinear value at cell ``at`` + ``frac`` (Σ corner weight · value; f = 0 axes skipped)."""
    value = None
    corners = [(0, 1.0)]
    for axis in range(3):
        f = float(frac[axis])
        if f > 0.0:
            corners = [(c + d, w * wd) for c, w in corners
                       for d, wd in ((0, 1.0 - f), (int(strides[axis]), f))]
    for c, w in corners:
        term = ev[at + c] if w == 1.0 else w * ev[at + c]
        value = term if value is None else value + term
    return value
