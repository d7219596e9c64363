"""Dose mode's batch rows: electron tables, their hard-event majorant, the coupled kernel call.

The majorant ``sig_hat[m, sp, i]`` bounds the total hard cross section σ = σ_δ + σ_brems
(+ σ_annih for positrons) over every energy a step starting in grid interval i can reach: a step
from E loses at most the fraction f (``max_energy_loss_fraction``) of E, so it stays within
[E(1 − f), E] ⊂ [T_{i−w}, T_{i+1}] with w = ⌈ln(1/(1 − f))/Δln T⌉ + 1. The kernels interpolate σ
linearly in ln T between nodes, so σ there never exceeds the largest node value of that window,
which is the majorant (times 1 + 1e-12 against rounding). Exact for the fictitious-event method
(:mod:`tetdose.transport.history._electron`); a larger f makes σ̂ larger and more events
fictitious, never biased.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from tetdose._typing import FloatArray
from tetdose.transport.physics.electron_xs import ElectronTables, build_electron_tables
from tetdose.transport.physics.xs import CrossSections
from tetdose.transport.run._dose_batches import run_world_dose
from tetdose.transport.run.settings import TransportSettings
from tetdose.transport.sources.arrays import E_MAX_MEV

#: Relative margin of the majorant against rounding.
MAJORANT_MARGIN = 1e-12


def hard_majorant(et: ElectronTables, f_loss: float) -> FloatArray:
    """(n_mat, 2, n_e) σ̂ [cm²/g] of the tables ``et`` for steps losing at most ``f_loss``."""
    total = np.array(et.sigma_delta) + np.array(et.sigma_brems)
    total[:, 1] += et.sigma_annih
    n = total.shape[2]
    w = math.ceil(math.log(1.0 / (1.0 - f_loss)) / et.d_ln_e) + 1
    out = np.empty_like(total)
    for i in range(n):
        out[:, :, i] = total[:, :, max(i - w, 0):min(i + 2, n)].max(axis=2)
    out *= 1.0 + MAJORANT_MARGIN
    out.flags.writeable = False
    return out


@lru_cache(maxsize=8)
def _tables(names: tuple[str, ...], cutoff_mev: float, photon_cutoff_mev: float,
            f_loss: float) -> tuple[ElectronTables, FloatArray]:
    et = build_electron_tables(names, cutoff_mev=cutoff_mev, photon_cutoff_mev=photon_cutoff_mev,
                               e_max_mev=E_MAX_MEV)
    return et, hard_majorant(et, f_loss)


def electron_tables(names: list[str], settings: TransportSettings
                    ) -> tuple[ElectronTables, FloatArray]:
    """Electron tables of the materials ``names`` for ``settings``' cut-offs, and their
    majorant (cached: phases and engines with the same materials share them)."""
    return _tables(tuple(names), settings.electron_cutoff_mev, settings.energy_cutoff_mev,
                   settings.max_energy_loss_fraction)


def run_dose_rows(job, xs: CrossSections, settings: TransportSettings,  # noqa: ANN001
                  b_start: int, b_stop: int, energy: FloatArray, ledger: FloatArray,
                  counts: np.ndarray) -> None:
    """Fill the rows of batches ``b_start … b_stop−1`` of a dose-mode
    :class:`~tetdose.transport.run.job.TransportJob` (arrays of ``b_stop − b_start`` rows)."""
    et, sig_hat = electron_tables(job.names, settings)
    ps = job.particles
    run_world_dose(*job.geom, xs, et, sig_hat, job.src, ps.electron, ps.positron, ps.volume,
                   ps.group_cdf, settings.seed, settings.stream, settings.n_histories,
                   settings.n_batches, b_start, b_stop, settings.energy_cutoff_mev,
                   settings.max_energy_loss_fraction, settings.photon_splitting,
                   settings.range_rejection_mev, energy, ledger, counts)
