"""Dose mode's batch rows: electron tables, their hard-event majorant, the photons' Woodcock
majorant, water's stopping-power row for dose to water, the coupled kernel call.

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
from collections.abc import Callable
from functools import lru_cache

import numpy as np

from tetdose._typing import FloatArray
from tetdose.transport.geometry._world import WorldGeometry
from tetdose.transport.geometry.tets import material_density_max
from tetdose.transport.physics.electron_xs import ElectronTables, build_electron_tables
from tetdose.transport.physics.materials import Material, resolve_material
from tetdose.transport.physics.xs import CrossSections
from tetdose.transport.run._dose_batches import run_world_dose
from tetdose.transport.run.settings import SPLITTING_SCHEMES, TransportSettings
from tetdose.transport.sources.arrays import E_MAX_MEV
from tetdose.transport.sources.quasi import history_points

#: Relative margin of the majorant against rounding.
MAJORANT_MARGIN = 1e-12
#: Relative margin of the photons' Woodcock majorant (rounding of a linear density evaluated
#: at a point up to 1e-9 mm outside its tet), and the floor of ln μ̂ [ln 1/cm] (vacuum).
PHOTON_MAJORANT_MARGIN = 1e-9
LN_MU_HAT_FLOOR = -700.0


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


def photon_majorant(xs: CrossSections, rho_max_g_cm3: FloatArray) -> FloatArray:
    """(n_E,) ln μ̂ [ln 1/cm] on the nodes of ``xs``: max over materials m of
    ln (μ/ρ)_m + ln ρ_max,m (``rho_max_g_cm3[m]``, materials of density 0 left out), times
    1 + :data:`PHOTON_MAJORANT_MARGIN`.

    The kernels interpolate ln μ linearly in ln E between the same nodes, so the majorant's
    interpolant bounds every material's at every energy, not only at the nodes
    (:mod:`tetdose.transport.history._delta`). All densities 0: μ̂ ≈ 0 (e^−700 /cm)."""
    rho = np.asarray(rho_max_g_cm3, dtype=np.float64)
    used = np.flatnonzero(rho > 0.0)
    out = np.full(xs.ln_mu_transported.shape[1], LN_MU_HAT_FLOOR)
    if len(used):
        out = np.maximum(out, (np.asarray(xs.ln_mu_transported)[used]
                               + np.log(rho[used])[:, None]).max(axis=0))
    out += math.log1p(PHOTON_MAJORANT_MARGIN)
    out.flags.writeable = False
    return out


def majorant_densities(geom: WorldGeometry, n_materials: int) -> FloatArray:
    """(n_materials,) ρ_max,m [g/cm³] of the photons' majorant: over the mesh's vertices and the
    voxels meeting its point-location box (``TetGeometry.rho_max``), or over every voxel of a
    voxel-only world (:mod:`tetdose.transport.history._delta`)."""
    if geom.tet.planes.shape[0] > 0:
        return geom.tet.rho_max
    return material_density_max(geom.vox.material, geom.vox.density, n_materials)


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


def water_stopping(names: list[str | Material], settings: TransportSettings) -> FloatArray:
    """(2, n_e) water's restricted total L/ρ [MeV cm²/g] on the grid of the run's electron
    tables (a writeable copy): water's own row when it is one of ``names`` (so a water cell's
    two dose-to-water sums are bitwise equal), else from water's tables built alike."""
    et, _ = electron_tables(names, settings)
    media = [resolve_material(m) for m in names]
    water = resolve_material("water")
    if water in media:
        return np.array(et.stopping[media.index(water)])
    alone, _ = electron_tables(["water"], settings)
    return np.array(alone.stopping[0])


def qmc_rows(settings: TransportSettings, b_start: int, b_stop: int) -> FloatArray:
    """Quasi-random source points of batches ``b_start … b_stop−1`` (the kernels' ``qmc``)."""
    first = b_start * settings.n_histories // settings.n_batches
    last = b_stop * settings.n_histories // settings.n_batches
    return history_points(settings.quasi_random, settings.seed, settings.stream,
                          settings.n_histories, settings.n_batches, first, last - first)


def dose_rows_call(job, xs: CrossSections, settings: TransportSettings,  # noqa: ANN001
                   b_start: int, b_stop: int, energy: FloatArray, ledger: FloatArray,
                   counts: np.ndarray, water: FloatArray) -> Callable[[int, int], None]:
    """``call(o_from, o_to)``: add histories ``o_from … o_to−1`` of each of the batches
    ``b_start … b_stop−1`` of a dose-mode :class:`~tetdose.transport.run.job.TransportJob` to
    their rows (arrays of ``b_stop − b_start`` rows; ``water`` (rows, 2, n_cells) the
    dose-to-water sums, n_cells 0 when not tallied)."""
    et, sig_hat = electron_tables(job.names, settings)
    l_water = water_stopping(job.names, settings) if water.shape[2] > 0 else np.zeros((2, 0))
    ps = job.particles
    ln_mu_hat = (photon_majorant(xs, majorant_densities(job.geom, len(job.names)))
                 if settings.photon_tracking == "woodcock" else np.zeros(0))
    qmc = qmc_rows(settings, b_start, b_stop)
    scheme = SPLITTING_SCHEMES.index(settings.splitting_scheme)

    def call(o_from: int, o_to: int) -> None:
        run_world_dose(*job.geom, xs, ln_mu_hat, et, sig_hat, job.src, ps.electron, ps.positron,
                       ps.volume, ps.group_cdf, settings.seed, settings.stream,
                       settings.n_histories, settings.n_batches, b_start, b_stop, o_from, o_to,
                       qmc, settings.energy_cutoff_mev, settings.max_energy_loss_fraction,
                       settings.photon_splitting, settings.secondary_copies, scheme,
                       settings.range_rejection_mev, energy,
                       ledger, counts, l_water, water)
    return call
