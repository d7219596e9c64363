"""DVHs with uncertainty bands, and every DVH point with its σ.

A dose d_i ± σ_i per element (tet or voxel; σ from the run's batches) is resampled R times as
d_i^(r) = max(d_i + σ_i z_i^(r), 0) with independent standard normal z (a parametric bootstrap:
Efron & Tibshirani, *An Introduction to the Bootstrap*, Chapman & Hall 1993, §6.5). Each replica
gives a DVH; a metric's σ (D95, D2, Dmean …) is the standard deviation of its replicas, the band
the 16th–84th percentile of V(D) over them (±1σ for a normal spread). The replicas scatter
around the measured dose, which already carries one draw of noise: the band is the spread a
repeated run would show, not a correction of the bias noise gives to near-minimum and
near-maximum metrics (noise widens a DVH: D98 reads low and D2 high).

Two DVH points differ significantly when |x_a − x_b| > :data:`COVERAGE` · sqrt(σ_a² + σ_b²)
(coverage factor k = 2, ~95 %: JCGM 100:2008, the GUM, §6.2).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from tetdose._typing import FloatArray
from tetdose.compare.dvh import DVH, dvh

#: Replicas drawn per DVH.
RESAMPLES = 40
#: Coverage factor of the significance flag.
COVERAGE = 2.0


@dataclass(frozen=True, eq=False)
class BandedDVH:
    """A DVH, its resampled replicas and the σ of each of its metrics."""

    dvh: DVH
    replicas: tuple[DVH, ...]

    @property
    def name(self) -> str:
        return self.dvh.name

    def metrics(self) -> dict[str, float]:
        return self.dvh.metrics()

    def metrics_sigma(self) -> dict[str, float]:
        """σ of each metric of :meth:`DVH.metrics` over the replicas (0 without σ)."""
        if not self.replicas:
            return dict.fromkeys(self.dvh.metrics(), 0.0)
        values = [r.metrics() for r in self.replicas]
        return {k: float(np.std([v[k] for v in values], ddof=1)) for k in values[0]}

    def band(self, levels_gy: FloatArray) -> tuple[FloatArray, FloatArray]:
        """16th and 84th percentile of V(D) [%] over the replicas at each level."""
        if not self.replicas:
            v = self.dvh.curve(levels_gy)
            return v, v
        curves = np.array([r.curve(levels_gy) for r in self.replicas])
        return np.percentile(curves, 16, axis=0), np.percentile(curves, 84, axis=0)


def banded_dvh(dose_gy: FloatArray, sigma_gy: FloatArray | None, weight: FloatArray, *,
               name: str = "", weight_kind: str = "volume", resamples: int = RESAMPLES,
               seed: int = 0) -> BandedDVH:
    """The DVH of ``dose_gy`` (weights ``weight``) and ``resamples`` replicas drawn with σ
    ``sigma_gy`` (module docstring); no replicas when σ is None or zero."""
    d = np.asarray(dose_gy, dtype=np.float64).ravel()
    base = dvh(d, weight, weight_kind=weight_kind, name=name)
    if sigma_gy is None or not np.any(np.asarray(sigma_gy) > 0):
        return BandedDVH(base, ())
    s = np.asarray(sigma_gy, dtype=np.float64).ravel()
    rng = np.random.default_rng(seed)
    reps = tuple(dvh(np.maximum(d + s * rng.standard_normal(d.size), 0.0), weight,
                     weight_kind=weight_kind, name=name) for _ in range(resamples))
    return BandedDVH(base, reps)


def compare_points(a: BandedDVH, b: BandedDVH) -> dict[str, dict[str, Any]]:
    """Per DVH metric: both values with σ, the difference a − b, its combined σ and whether it
    exceeds :data:`COVERAGE` times that σ."""
    ma, mb, sa, sb = a.metrics(), b.metrics(), a.metrics_sigma(), b.metrics_sigma()
    out = {}
    for k in ma:
        diff, sigma = ma[k] - mb[k], float(np.hypot(sa[k], sb[k]))
        out[k] = {a.name: ma[k], f"{a.name}_sigma": sa[k], b.name: mb[k],
                  f"{b.name}_sigma": sb[k], "difference": diff, "difference_sigma": sigma,
                  "significant": bool(abs(diff) > COVERAGE * sigma)}
    return out
