"""The patient's breathing phase in time: a recorded trace or a regular cycle.

Either gives the phase of a :class:`~tetdose.motion.phases.PhaseSeries` the patient is in at
every instant, as piecewise-constant intervals (``starts_s``, ``phase_index``) for
:func:`tetdose.plan.phase_split.split_by_phase`.

* **Regular cycle** of period T [s] starting at cycle percent φ₀: at time t the patient is at
  φ(t) = φ₀ + 100 t / T (mod 100), in the phase whose percent is nearest φ (cyclically), so a
  phase of percent p_k holds the cycle from the midpoint with its predecessor to the midpoint
  with its successor; equally spaced phases each get 1/K of the time. The phase changes are
  exact: the instants where φ(t) crosses a midpoint.
* **Trace** (CSV, a header row, columns ``time_s`` and either ``phase_percent`` or
  ``amplitude_mm``; e.g. a respiratory monitor's record): each sample holds from the midpoint
  with the previous sample's time to the midpoint with the next. A phase percent goes to the
  nearest phase (cyclically). An amplitude goes to the phase of nearest amplitude on the same
  branch of the cycle (rising or falling, from the neighbouring samples; a phase's branch from
  its neighbours' amplitudes; extremes match either branch), the phases' amplitudes being given
  in phase order (e.g. the tumour's superior–inferior position in each phase of the 4D-CT).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tetdose._typing import FloatArray, IntArray
from tetdose.errors import OptionError

TRACE_KINDS = ("phase_percent", "amplitude_mm")


def nearest_phase(percent: FloatArray, phase_percent: FloatArray) -> IntArray:
    """Index of the phase whose percent is cyclically nearest to each of ``percent``."""
    d = np.abs((np.asarray(percent, dtype=np.float64)[:, None] - np.asarray(phase_percent)[None])
               % 100.0)
    return np.argmin(np.minimum(d, 100.0 - d), axis=1)


def regular_cycle(period_s: float, start_percent: float, phase_percent: Sequence[float],
                  end_s: float) -> tuple[FloatArray, IntArray]:
    """(starts [s], phase index) of a regular cycle over [0, ``end_s``] (module doc)."""
    if not (np.isfinite(period_s) and period_s > 0.0):
        raise OptionError(f"--breathing-period-s {period_s} must be a positive number of seconds")
    if not 0.0 <= start_percent < 100.0:
        raise OptionError(f"--start-phase {start_percent} must be a cycle percent in [0, 100)")
    p = np.sort(np.asarray(phase_percent, dtype=np.float64) % 100.0)
    mids = 0.5 * (p + np.roll(p, -1) + np.r_[np.zeros(len(p) - 1), 100.0]) % 100.0
    turns = np.arange(np.floor(start_percent / 100.0) - 1,
                      np.ceil((start_percent + 100.0 * end_s / period_s) / 100.0) + 1)
    levels = np.sort((mids[None, :] + 100.0 * turns[:, None]).ravel())
    cross = (levels - start_percent) * period_s / 100.0
    after = np.unique(cross[cross > 0.0])  # levels reach a turn past end_s
    starts = np.r_[0.0, after[after < end_s]]
    ends = after[:len(starts)]
    centre = start_percent + 100.0 * 0.5 * (starts + ends) / period_s
    return _merged(starts, nearest_phase(centre, phase_percent))


@dataclass(frozen=True, eq=False)
class BreathingTrace:
    """A recorded trace: sample times [s] and values (``kind``: phase percent or amplitude
    [mm]) and where it came from."""

    times_s: FloatArray
    values: FloatArray
    kind: str
    source: str = ""

    def __post_init__(self) -> None:
        t = np.asarray(self.times_s, dtype=np.float64).reshape(-1)
        v = np.asarray(self.values, dtype=np.float64).reshape(-1)
        where = self.source or "the breathing trace"
        if self.kind not in TRACE_KINDS:
            raise OptionError(f"{where}: trace kind {self.kind!r} is unknown; use {TRACE_KINDS}")
        if len(t) < 2 or len(t) != len(v) or not np.all(np.isfinite(t)) or not np.all(
                np.isfinite(v)):
            raise OptionError(f"{where}: needs at least two rows of finite time_s and "
                              f"{self.kind}")
        if np.any(np.diff(t) <= 0.0):
            raise OptionError(f"{where}: time_s must increase from row to row")
        if self.kind == "phase_percent" and (v.min() < 0.0 or v.max() > 100.0):
            raise OptionError(f"{where}: phase_percent must lie in [0, 100]")
        object.__setattr__(self, "times_s", t)
        object.__setattr__(self, "values", v)

    @property
    def duration_s(self) -> float:
        return float(self.times_s[-1] - self.times_s[0])

    @classmethod
    def read(cls, path: str | os.PathLike[str]) -> BreathingTrace:
        """A CSV trace with a header row: ``time_s`` and ``phase_percent`` or ``amplitude_mm``."""
        path = Path(path)
        try:
            lines = [ln for ln in path.read_text().splitlines() if ln.strip()
                     and not ln.lstrip().startswith("#")]
        except OSError as exc:
            raise OptionError(f"cannot read breathing trace {path}: {exc.strerror}") from exc
        header = [h.strip() for h in lines[0].split(",")] if lines else []
        kinds = [k for k in TRACE_KINDS if k in header]
        if "time_s" not in header or len(kinds) != 1:
            raise OptionError(f"{path}: the header must name time_s and one of {TRACE_KINDS}, "
                              f"got {header}")
        try:
            rows = np.array([[float(x) for x in ln.split(",")] for ln in lines[1:]])
        except ValueError:
            raise OptionError(f"{path}: every row after the header must hold numbers") from None
        if rows.ndim != 2 or rows.shape[1] != len(header):
            raise OptionError(f"{path}: every row needs {len(header)} values")
        return cls(rows[:, header.index("time_s")], rows[:, header.index(kinds[0])], kinds[0],
                   str(path))

    def intervals(self, phase_percent: Sequence[float],
                  phase_amplitude_mm: Sequence[float] | None = None
                  ) -> tuple[FloatArray, IntArray]:
        """(starts [s], phase index) of the trace (module doc); amplitudes need the phases'
        ``phase_amplitude_mm`` in phase order."""
        t = self.times_s
        if self.kind == "phase_percent":
            idx = nearest_phase(self.values, phase_percent)
        else:
            if phase_amplitude_mm is None or len(phase_amplitude_mm) != len(phase_percent):
                raise OptionError(f"an amplitude trace needs the amplitude of each of the "
                                  f"{len(phase_percent)} phases (--phase-amplitudes-mm)")
            idx = amplitude_phase(self.values, np.asarray(phase_amplitude_mm, dtype=np.float64))
        starts = np.r_[t[0], 0.5 * (t[1:] + t[:-1])]
        return _merged(starts, idx)


def amplitude_phase(amplitude_mm: FloatArray, phase_amplitude_mm: FloatArray) -> IntArray:
    """Phase index of each trace sample: nearest amplitude on the same branch (module doc)."""
    a = np.asarray(amplitude_mm, dtype=np.float64)
    trend = np.sign(np.gradient(a))
    pa = phase_amplitude_mm
    branch = np.sign(np.roll(pa, -1) - np.roll(pa, 1))
    same = (branch[None, :] == trend[:, None]) | (branch[None, :] == 0) | (trend[:, None] == 0)
    d = np.abs(a[:, None] - pa[None, :])
    return np.argmin(np.where(same, d, d + 1e12), axis=1)


def _merged(starts: FloatArray, idx: IntArray) -> tuple[FloatArray, IntArray]:
    """Consecutive intervals of the same phase joined."""
    keep = np.r_[True, idx[1:] != idx[:-1]]
    return starts[keep], np.asarray(idx[keep], dtype=np.int64)
