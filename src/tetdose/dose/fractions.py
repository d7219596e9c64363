"""A course of interplay fractions against the time-weighted 4D dose and the static plan.

Fraction f (1..N) is :func:`tetdose.dose.interplay.run_interplay` with its own start in the
breathing cycle (random streams f·K + p, so fractions and the time-weighted run, streams
0..K−1, are independent). The course's mean dose per fraction is the energy over the mass,
D̄ = Σ_f E_f / Σ_f m_f per tet, and converges to the time-weighted 4D dose as N grows (the
interplay averages out, Bortfeld et al., Phys. Med. Biol. 47:2203, 2002; the per-fraction spread
of a target metric shrinks about as 1/√n over n fractions). The static plan is one phase of the
time-weighted run (``static_phase``, default 0): the whole plan on the planning geometry, run
again with K·n histories (stream (N + 1)·K + p) so that its per-tet noise is that of the 4D
and fraction doses (a noisier dose has a lower D95 and a higher D2).

The target's D95, D2 (dose to the hottest 95 %, 2 % of its mass) and mean dose are reported per
fraction, for the mean of the course and for both references; the spread of the mean of n
fractions is estimated from subsets of the N fractions drawn without replacement, times
√((N − 1)/(N − n)) (the finite-population correction, Cochran, Sampling Techniques, 1977, §2.5:
the spread of an n-fraction course of independent random starts).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from tetdose._typing import FloatArray
from tetdose.dose.dose4d import Dose4D, run_dose4d
from tetdose.dose.interplay import check_interplay_plan, run_interplay
from tetdose.motion.phases import PhaseSeries
from tetdose.plan.delivery import Timeline
from tetdose.plan.prescription import dose_metric, region_cells, region_label
from tetdose.transport import Plan, TransportSettings

METRICS = ("D95", "D2", "mean")
#: Subsets drawn per course length for the spread of an n-fraction mean.
SUBSETS = 400


@dataclass(frozen=True)
class Start:
    """Where a fraction starts: the phase intervals (``starts_s``, ``phase_index``), the
    delivery's start ``t0_s`` on their clock and a JSON record of the trace/cycle."""

    starts_s: FloatArray
    phase_index: FloatArray
    t0_s: float
    trace: dict[str, Any]


@dataclass(frozen=True, eq=False)
class FractionCourse:
    """N interplay fractions, the time-weighted 4D run and the target's cells."""

    fractions: list[Dose4D]
    time_weighted: Dose4D
    target: np.ndarray  # boolean mask of the target's tets
    target_name: str
    static: Dose4D  # the whole plan on the static phase alone

    def mean_dose(self, which: Sequence[int] | None = None) -> FloatArray:
        """D̄ [Gy per fraction, the runs' unit] of fractions ``which`` (default all)."""
        fr = [self.fractions[i] for i in (range(len(self.fractions)) if which is None
                                           else which)]
        energy = sum(f.accumulated.dose_gy * f.accumulated.mass_g for f in fr)
        mass = sum(f.accumulated.mass_g for f in fr)
        return np.divide(energy, mass, out=np.zeros_like(mass), where=mass > 0)

    def metrics(self, dose_gy: FloatArray, mass_g: FloatArray) -> dict[str, float]:
        t = self.target
        return {m: dose_metric(dose_gy[t], mass_g[t], m) for m in METRICS}

    def report(self, seed: int = 1) -> dict[str, Any]:
        """Per-fraction metrics, their mean and spread, the course's mean against the
        time-weighted 4D dose and the static plan, and the spread of n-fraction means."""
        acc = self.time_weighted.accumulated
        per = [self.metrics(f.accumulated.dose_gy, f.accumulated.mass_g) for f in self.fractions]
        static = self.static.results[0].mesh_part()
        out: dict[str, Any] = {
            "target": self.target_name, "fractions": len(per), "per_fraction": per,
            "fraction_mean": {m: float(np.mean([p[m] for p in per])) for m in METRICS},
            "fraction_sd": {m: float(np.std([p[m] for p in per], ddof=1)) if len(per) > 1
                            else 0.0 for m in METRICS},
            "course_mean": self.metrics(self.mean_dose(), acc.mass_g),
            "time_weighted_4d": self.metrics(acc.dose_gy, acc.mass_g),
            "static_plan": self.metrics(static.dose_gy, static.mass_g),
            "static_phase_percent": float(self.static.series.phase_percent[0]),
            "statistical_rel_sd_mean_dose": self._noise(),
            "spread_of_n_fraction_mean": self._spread(seed)}
        return out

    def _noise(self) -> float:
        """Relative σ (Monte Carlo) of the target's mean dose in one fraction, the mean over
        fractions, as if tets were independent (σ² = Σ m² σ_k² / (Σ m)²): a lower bound, since
        one photon doses many tets (README: about a third of the true σ on the lung CT)."""
        t, out = self.target, []
        for f in self.fractions:
            a = f.accumulated
            if a.dose_std_gy is None:
                return float("nan")
            m, d, s = a.mass_g[t], a.dose_gy[t], a.dose_std_gy[t]
            out.append(float(np.sqrt(np.sum((m * s) ** 2)) / max(np.sum(m * d), 1e-300)))
        return float(np.mean(out))

    def _spread(self, seed: int) -> list[dict[str, float]]:
        """SD of the D95 and mean dose of an n-fraction mean (module doc)."""
        n_all = len(self.fractions)
        rng = np.random.default_rng(seed)
        mass = self.time_weighted.accumulated.mass_g
        sizes = sorted({n for n in (1, 2, 3, 5, 10, 20, 30, n_all) if n <= max(1, n_all - 1)})
        out = []
        for n in sizes:
            vals = [self.metrics(self.mean_dose(rng.choice(n_all, n, replace=False)), mass)
                    for _ in range(SUBSETS if n < n_all else 1)]
            fpc = np.sqrt((n_all - 1) / (n_all - n)) if n < n_all else 1.0
            out.append({"n": n, **{f"sd_{m}": float(fpc * np.std([v[m] for v in vals]))
                                   for m in ("D95", "mean")}})
        return out


def run_fractions(series: PhaseSeries, plan: Plan, settings: TransportSettings,
                  timeline: Timeline, starts: Sequence[Start], target: str | int,
                  static_phase: int = 0, **kwargs: Any) -> FractionCourse:  # noqa: ANN401
    """The time-weighted 4D run and one interplay fraction per ``starts`` (module doc);
    ``kwargs`` as :func:`~tetdose.dose.interplay.run_interplay` (``ct_hu``, ``phase_ct``, ...)."""
    check_interplay_plan(plan)
    plan = plan.resolved(series.reference)
    mask = region_cells(series.reference, None, region_label(target, plan.regions))
    tw = run_dose4d(series, plan, settings, **kwargs)
    if tw.voxel is not None:  # the phases' bodies, computed once
        kwargs = {**kwargs, "phase_density": tw.voxel.density}
    static = _static(series, plan, settings, static_phase, len(starts), kwargs)
    fr = [run_interplay(series, plan, settings, timeline, s.starts_s, s.phase_index,
                        t0_s=s.t0_s, fraction=f + 1, trace=s.trace, **kwargs)
          for f, s in enumerate(starts)]
    return FractionCourse(fr, tw, mask, str(target), static)


def _static(series: PhaseSeries, plan: Plan, settings: TransportSettings, p: int,
            n_fractions: int, kwargs: dict[str, Any]) -> Dose4D:
    """The whole plan on phase ``p`` alone with K·n histories (module doc)."""
    k = series.n_phases
    one = PhaseSeries(series.reference, series.points_mm[[p]], series.phase_percent[[p]], None,
                      None if series.density_g_cm3 is None else series.density_g_cm3[[p]])
    pick = {name: None if kwargs.get(name) is None else [kwargs[name][p]]
            for name in ("phase_ct", "dvfs", "phase_density")}
    st = replace(settings, n_histories=settings.n_histories * k, stream=(n_fractions + 1) * k + p)
    return run_dose4d(one, plan, settings, phase_plans=[plan], phase_settings=[st],
                      **{**kwargs, **pick})
