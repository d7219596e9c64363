"""Two Monte Carlo doses compared with their uncertainties: what is physics, what is noise.

Point i of a structure holds the evaluated dose a_i ± σ_a,i and the reference dose b_i ± σ_b,i
(σ: the standard deviation of each dose, from its batches; a dose without σ counts as exact).

**Mean relative difference** (:func:`mean_rel_diff`), over elements of weight w_i (mass or
volume): R = Σ w_i a_i / Σ w_i b_i − 1, and its 1σ by first-order propagation with the points
independent, σ_R = sqrt(Σ w_i² (σ_a,i² + (1 + R)² σ_b,i²)) / Σ w_i b_i.

**Systematic part** (:func:`systematic_fit`). Kawrakow & Fippel (Phys. Med. Biol. 45:2163,
2000, §"comparing two Monte Carlo distributions") histogram Δ_i/σ_i and fit it as a Gaussian of
unit width (the statistical part) plus a fraction f of points displaced by a systematic
difference. Here the same model is fitted by maximum likelihood on the points themselves, not on
a histogram (a two-component mixture with known variances: McLachlan & Peel, *Finite Mixture
Models*, Wiley 2000, ch. 1–2), with the difference relative to the reference's true dose t_i: a
fraction f of the points has E[a_i] = (1 + δ)·t_i, the rest E[a_i] = t_i. With v_i = σ_a,i² +
σ_b,i² and m_i = (a_i σ_b,i² + b_i σ_a,i²)/v_i the inverse-variance weighted mean of both doses
(E m_i = (1 + δ σ_b,i²/v_i)·t_i for the shifted points),

    Δ_i = a_i − b_i,   s_i(δ) = δ·m_i / (1 + δ σ_b,i²/v_i),
    ℓ(δ, f) = Σ_i log[ (1 − f)·N(Δ_i; 0, v_i) + f·N(Δ_i; s_i(δ), v_i) ].

m_i is uncorrelated with Δ_i when the σ are the true ones (cov = σ_a²σ_b² − σ_b²σ_a² = 0), so
the noisy dose scale does not bias δ (errors in variables, as a shift ∝ b_i or ∝ (a_i + b_i)/2
would when the two doses' noise differs). The σ entering v_i and m_i are pooled
(:func:`pooled_sigma`): a σ from B batches is itself uncertain (B − 1 degrees of freedom), and a
mixture fitted with raw batch σ finds a spurious "systematic" fraction among the points whose σ
came out low — measured: 2Δℓ ≈ 40 between two unbiased runs with 10 batches, ≈ 0 once pooled.
ℓ is concave in f: for each δ on a grid f is found by bisection of ∂ℓ/∂f, then
δ is refined (Brent). Three nested models are weighed by the Bayesian information criterion
(Schwarz, Ann. Stat. 6:461, 1978): *none* (the doses agree within their noise), *all* (f = 1:
one systematic difference everywhere, e.g. a scale) and *part* (0 < f < 1: a difference in part
of the structure). σ of δ and f: the inverse of the observed information (numerical Hessian of
−ℓ). When *none* wins, ``systematic_fraction`` is 0 and ``systematic_rel_diff`` is the *all*
model's δ with its σ: the size of a common difference the data still allow, consistent with
zero. Each point's posterior probability of carrying the difference, f·p_1/((1 − f)·p_0 + f·p_1),
says where it sits.

Points whose σ are both zero cannot be judged and are left out; the points' noise is taken as
independent (a mesh dose put on voxels correlates neighbouring voxels that share a tet, which
makes the σ of δ somewhat optimistic).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import optimize, special

from tetdose._typing import FloatArray

#: Grid of relative systematic differences searched before refinement (|δ| ≤ 50 %; beyond, the
#: doses differ by more than any comparison of noise needs to tell).
DELTA_GRID = np.linspace(-0.5, 0.5, 101)
#: At most this many points enter the mixture fit (a seeded uniform sample beyond).
FIT_MAX_POINTS = 50_000
#: Points pooled for each σ (:func:`pooled_sigma`).
POOL_POINTS = 51
#: A normalised difference |Δ/σ| above this marks a point as significant in the maps.
Z_SIGNIFICANT = 3.0
MODELS = ("none", "all", "part")
#: Above this median relative σ of a − b the Gaussian mixture is not fitted: with σ pooled from
#: noisy doses and skewed per-point noise it reports spurious parts (measured: two unbiased
#: runs at 30 % and 10 % per point → "part", δ = −45 %; the --quick demo's 30–50 % per voxel).
MAX_REL_SIGMA = 0.2


@dataclass(frozen=True)
class SystematicFit:
    """The fitted systematic part: δ (relative to the reference) and the fraction f carrying it,
    with their 1σ; the model chosen; the number of points; the log-likelihood of each model."""

    delta: float
    delta_sigma: float
    fraction: float
    fraction_sigma: float
    model: str
    n_points: int
    log_likelihood: dict[str, float]

    def summary(self) -> dict[str, Any]:
        return {"systematic_rel_diff": self.delta, "systematic_rel_diff_sigma": self.delta_sigma,
                "systematic_fraction": self.fraction,
                "systematic_fraction_sigma": self.fraction_sigma,
                "systematic_model": self.model, "systematic_points": self.n_points}


def combined_sigma(sa: FloatArray, sb: FloatArray) -> FloatArray:
    """σ of a − b for independent doses: sqrt(σ_a² + σ_b²)."""
    return np.sqrt(np.asarray(sa, float) ** 2 + np.asarray(sb, float) ** 2)


def normalised_difference(a: FloatArray, sa: FloatArray, b: FloatArray, sb: FloatArray
                          ) -> FloatArray:
    """Δ/σ = (a − b)/sqrt(σ_a² + σ_b²); NaN where both σ are zero."""
    s = combined_sigma(sa, sb)
    d = np.asarray(a, float) - np.asarray(b, float)
    return np.divide(d, s, out=np.full(d.shape, np.nan), where=s > 0)


def pooled_sigma(d: FloatArray, s: FloatArray, w: FloatArray | None = None,
                 k: int = POOL_POINTS) -> FloatArray:
    """σ_i re-estimated from the ``k`` points nearest in deposited energy d·w (w: mass or volume;
    1 without): d_i·sqrt(mean of (σ_j/d_j)² over them). A batch σ is itself noisy (B − 1 degrees
    of freedom); the relative σ of a Monte Carlo dose is a smooth function of the energy scored,
    so the pooled σ is nearly exact (module docstring). Zero where d or σ is zero."""
    d, s = np.asarray(d, float).ravel(), np.asarray(s, float).ravel()
    e = d * (1.0 if w is None else np.asarray(w, float).ravel())
    ok = (d > 0) & (s > 0)
    out = np.zeros_like(d)
    n = int(ok.sum())
    if n == 0:
        return out
    idx = np.flatnonzero(ok)[np.argsort(e[ok], kind="stable")]
    rel2 = (s[idx] / d[idx]) ** 2
    k = min(k, n)
    c = np.r_[0.0, np.cumsum(rel2)]
    lo = np.clip(np.arange(n) - k // 2, 0, n - k)
    out[idx] = d[idx] * np.sqrt((c[lo + k] - c[lo]) / k)
    return out


def mean_rel_diff(a: FloatArray, sa: FloatArray, b: FloatArray, sb: FloatArray, w: FloatArray
                  ) -> tuple[float, float]:
    """(R, σ_R): the weighted mean relative difference of a to b and its 1σ (module docstring)."""
    a, sa, b, sb, w = (np.asarray(x, float).ravel() for x in (a, sa, b, sb, w))
    den = float(np.dot(w, b))
    if not den > 0:
        return float("nan"), float("nan")
    r = float(np.dot(w, a)) / den - 1.0
    var = float(np.dot(w**2, sa**2 + (1.0 + r) ** 2 * sb**2))
    return r, float(np.sqrt(var)) / den


class _Likelihood:
    """ℓ(δ, f) of the points (module docstring), with f profiled out on demand."""

    def __init__(self, a: FloatArray, sa: FloatArray, b: FloatArray, sb: FloatArray,
                 ) -> None:
        va, vb = sa**2, sb**2
        self.v = va + vb
        self.diff = a - b
        self.w_b = vb / self.v
        # inverse-variance weighted mean: uncorrelated with a − b when the σ are the true ones
        self.mean = (a * vb + b * va) / self.v
        self.log_p0 = -0.5 * (np.log(2.0 * np.pi * self.v) + self.diff**2 / self.v)

    def shift(self, delta: float) -> FloatArray:
        """E[a − b] = δ·t with t the reference's true dose, through E[m] = (1 + δ·σ_b²/v)·t."""
        return delta * self.mean / (1.0 + delta * self.w_b)

    def log_ratio(self, delta: float) -> FloatArray:
        """log p_1(δ)/p_0 per point (normal densities of equal variance)."""
        s = self.shift(delta)
        return np.clip((2.0 * self.diff - s) * s / (2.0 * self.v), -700.0, 700.0)

    def value(self, delta: float, f: float) -> float:
        mix = np.logaddexp(np.log1p(-f) if f < 1.0 else -np.inf,
                           (np.log(f) if f > 0.0 else -np.inf) + self.log_ratio(delta))
        return float(self.log_p0.sum() + mix.sum())

    def best_fraction(self, delta: float) -> float:
        """argmax_f ℓ(δ, f) on [0, 1] (ℓ concave in f: bisection of ∂ℓ/∂f)."""
        q = np.exp(self.log_ratio(delta))

        def slope(f: float) -> float:
            return float(np.sum((q - 1.0) / ((1.0 - f) + f * q)))

        if slope(0.0) <= 0.0:
            return 0.0
        if slope(1.0) >= 0.0:
            return 1.0
        lo, hi = 0.0, 1.0
        for _ in range(40):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if slope(mid) > 0 else (lo, mid)
        return 0.5 * (lo + hi)

    def fit(self, fixed_f: float | None) -> tuple[float, float, float]:
        """(δ, f, ℓ) maximising ℓ, with f free (None) or fixed."""
        def neg(delta: float) -> float:
            f = self.best_fraction(delta) if fixed_f is None else fixed_f
            return -self.value(delta, f)

        values = [neg(d) for d in DELTA_GRID]
        i = int(np.argmin(values))
        step = DELTA_GRID[1] - DELTA_GRID[0]
        res = optimize.minimize_scalar(neg, bounds=(DELTA_GRID[i] - step, DELTA_GRID[i] + step),
                                       method="bounded", options={"xatol": 1e-6})
        delta = float(res.x) if res.fun <= values[i] else float(DELTA_GRID[i])
        f = self.best_fraction(delta) if fixed_f is None else fixed_f
        return delta, f, self.value(delta, f)

    def sigmas(self, delta: float, f: float, free_f: bool) -> tuple[float, float]:
        """1σ of δ and f from the observed information (numerical Hessian of −ℓ); f on its
        bound (or fixed) is held there."""
        hd, hf = 1e-4, 1e-3
        l0 = self.value(delta, f)
        d2d = (self.value(delta + hd, f) - 2 * l0 + self.value(delta - hd, f)) / hd**2
        if not free_f or f - hf < 0.0 or f + hf > 1.0:
            return _inv_sqrt(-d2d), 0.0
        d2f = (self.value(delta, f + hf) - 2 * l0 + self.value(delta, f - hf)) / hf**2
        dfd = (self.value(delta + hd, f + hf) - self.value(delta + hd, f - hf)
               - self.value(delta - hd, f + hf) + self.value(delta - hd, f - hf)) / (4 * hd * hf)
        info = -np.array([[d2d, dfd], [dfd, d2f]])
        try:
            cov = np.linalg.inv(info)
        except np.linalg.LinAlgError:
            return float("nan"), float("nan")
        return float(np.sqrt(max(cov[0, 0], 0.0))), float(np.sqrt(max(cov[1, 1], 0.0)))

    def posterior(self, delta: float, f: float) -> FloatArray:
        """Each point's probability of carrying the systematic difference."""
        q = f * np.exp(self.log_ratio(delta))
        return q / (1.0 - f + q)


def _inv_sqrt(x: float) -> float:
    return float(1.0 / np.sqrt(x)) if x > 0 else float("nan")


def _usable(a: FloatArray, sa: FloatArray, b: FloatArray, sb: FloatArray) -> np.ndarray:
    return (np.isfinite(a) & np.isfinite(b) & (combined_sigma(sa, sb) > 0)
            & ((a > 0) | (b > 0)))


def systematic_fit(a: FloatArray, sa: FloatArray, b: FloatArray, sb: FloatArray, *,
                   weight: FloatArray | None = None, pool: bool = True, seed: int = 0
                   ) -> tuple[SystematicFit, FloatArray]:
    """The systematic part of a − b (module docstring) and each point's posterior probability of
    carrying it (NaN where the point cannot be judged). ``pool``: σ of each dose pooled over
    neighbours in deposited energy (:func:`pooled_sigma`, ``weight`` the elements' mass or
    volume); off: the σ are taken as exact."""
    a, sa, b, sb = (np.asarray(x, float).ravel() for x in (a, sa, b, sb))
    keep = np.flatnonzero(_usable(a, sa, b, sb))
    posterior = np.full(a.shape, np.nan)
    if len(keep) < 2:
        nan = float("nan")
        return SystematicFit(nan, nan, nan, nan, "not enough points with σ", len(keep), {}), \
            posterior
    w = None if weight is None else np.asarray(weight, float).ravel()[keep]
    a, b, sa, sb = a[keep], b[keep], sa[keep], sb[keep]
    if pool:
        sa, sb = pooled_sigma(a, sa, w), pooled_sigma(b, sb, w)
    rel = np.median(combined_sigma(sa, sb) / np.maximum(0.5 * (a + b), 1e-300))
    if rel > MAX_REL_SIGMA:
        nan = float("nan")
        return SystematicFit(nan, nan, nan, nan, f"noise too high to separate a systematic part "
                             f"(median σ(a − b)/D = {100 * rel:.0f} % > "
                             f"{100 * MAX_REL_SIGMA:.0f} %): only the mean relative difference "
                             "is meaningful", len(keep), {}), posterior
    fit_idx = np.arange(len(keep))
    if len(keep) > FIT_MAX_POINTS:
        fit_idx = np.sort(np.random.default_rng(seed).choice(len(keep), FIT_MAX_POINTS,
                                                             replace=False))
    lik = _Likelihood(a[fit_idx], sa[fit_idx], b[fit_idx], sb[fit_idx])
    n = len(fit_idx)
    l_none = lik.value(0.0, 0.0)
    d_all, _, l_all = lik.fit(1.0)
    d_part, f_part, l_part = lik.fit(None)
    bic = {"none": -2 * l_none, "all": -2 * l_all + np.log(n),
           "part": -2 * l_part + 2 * np.log(n)}
    model = min(MODELS, key=lambda m: bic[m])
    if model == "part" and f_part >= 1.0:
        model = "all"
    if model == "part":
        delta, f = d_part, f_part
        s_delta, s_f = lik.sigmas(d_part, f_part, free_f=True)
    else:  # "none" reports the common difference the data allow, carried by no point
        delta, f, s_f = d_all, (1.0 if model == "all" else 0.0), 0.0
        s_delta, _ = lik.sigmas(d_all, 1.0, free_f=False)
    posterior[keep] = _Likelihood(a, sa, b, sb).posterior(delta, f)
    fit = SystematicFit(float(delta), float(s_delta), float(f), float(s_f), model, n,
                        {"none": l_none, "all": l_all, "part": l_part})
    return fit, posterior


def structure_significance(a: FloatArray, sa: FloatArray, b: FloatArray, sb: FloatArray,
                           w: FloatArray, fit_points: np.ndarray) -> tuple[dict[str, Any],
                                                                           FloatArray]:
    """Summary of one structure (flat arrays over its elements, weights ``w``: mass or volume):
    the mean relative difference over all its elements and the systematic part over
    ``fit_points`` (boolean, e.g. the elements above the dose threshold); returns (summary,
    posterior probability of the systematic part over the elements, NaN where not fitted)."""
    a, sa, b, sb, w = (np.asarray(x, float).ravel() for x in (a, sa, b, sb, w))
    fit_points = np.asarray(fit_points, bool).ravel()
    r, s_r = mean_rel_diff(a, sa, b, sb, w)
    out: dict[str, Any] = {"mean_rel_diff": r, "mean_rel_diff_sigma": s_r,
                           "mean_rel_diff_consistent_with_zero": bool(abs(r) <= 2.0 * s_r)}
    posterior = np.full(a.shape, np.nan)
    if not (np.any(sa > 0) or np.any(sb > 0)):
        out |= {"systematic_rel_diff": None, "systematic_fraction": None,
                "systematic_model": "no σ: both doses compared as exact, the statistical part "
                                    "cannot be separated"}
        return out, posterior
    fit, post = systematic_fit(a[fit_points], sa[fit_points], b[fit_points], sb[fit_points],
                               weight=w[fit_points])
    posterior[fit_points] = post
    z = normalised_difference(a, sa, b, sb)[fit_points]
    z = z[np.isfinite(z)]
    summary = fit.summary()
    if not np.isfinite(fit.delta):
        summary |= {"systematic_rel_diff": None, "systematic_fraction": None}
    out |= summary | {
        "points_significant": int((np.abs(z) > Z_SIGNIFICANT).sum()),
        "points_significant_expected": float(len(z) * special.erfc(Z_SIGNIFICANT / np.sqrt(2))),
        "normalised_difference_rms": float(np.sqrt(np.mean(z**2))) if z.size else float("nan")}
    return out, posterior
