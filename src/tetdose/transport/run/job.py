"""A transport run as a unit of work: world → kernel arrays (:class:`TransportJob`), batch rows
anywhere (:func:`run_batches`: this process's threads or a dask worker), rows → :class:`DoseResult`.

Every batch row depends only on the seed, the batch index and the inputs (counter-based streams),
so rows computed anywhere are bitwise the same; :mod:`tetdose.transport.run.distributed` ships jobs
to dask workers and assembles with the same :func:`assemble`.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, replace
from typing import NamedTuple

import numba
import numpy as np
from tqdm.auto import tqdm

from tetdose._typing import BoolArray, FloatArray, IntArray
from tetdose._version import __version__
from tetdose.core.image import ImageGrid
from tetdose.errors import PlanError
from tetdose.plan.model import Plan
from tetdose.transport.geometry._world import WorldGeometry
from tetdose.transport.geometry.world import MeshOnGrid, World, world_arrays
from tetdose.transport.history._electron import N_COUNTS_DOSE, N_LEDGER_DOSE
from tetdose.transport.history._photon import C_MISSED, N_COUNTS, N_LEDGER
from tetdose.transport.history.result import DoseResult
from tetdose.transport.physics.materials import Material, resolve_material
from tetdose.transport.physics.xs import (
    DENSITY_CLASS_MATERIALS,
    CrossSections,
    build_cross_sections,
    material_for_density,
)
from tetdose.transport.run._batches import run_world
from tetdose.transport.run.coupled import dose_rows_call, qmc_rows
from tetdose.transport.run.settings import TransportSettings
from tetdose.transport.run.water import convert
from tetdose.transport.sources._sample import SourceArrays
from tetdose.transport.sources.arrays import E_MAX_MEV, source_arrays
from tetdose.transport.sources.species import (
    ParticleSources,
    particle_sources,
    refuse_in_kerma_mode,
    source_mix,
)
from tetdose.transport.sources.volume import volume_arrays

#: Batches per kernel call and thread (groups keep the progress bar moving).
BATCH_GROUP_PER_THREAD = 2
#: Wall time [s] a kernel call aims at (:class:`Pace`): Python gets control between calls, so
#: Ctrl-C and SIGTERM stop a run within about this (a numba kernel cannot be interrupted). The
#: price: the threads wait for the slowest at the end of every call (estimated 1–3 % when a
#: call holds only ~10³ coupled histories per thread); the split itself costs no measurable CPU
#: (one thread, CPU time of the split run / the whole run: 0.95–1.02).
CALL_S = 1.0
#: Histories per batch of a run's first kernel call; later calls adapt (×1/4 … ×8 per call).
FIRST_CALL_HISTORIES = 32
#: The progress bar appears only for runs longer than this [s].
PROGRESS_DELAY_S = 2.0
#: Histories of the pilot run that checks the beams reach the world and times a history.
PILOT_HISTORIES = 1000
#: Fewest batches before a target uncertainty may stop a run (the batch σ needs a few).
MIN_TARGET_BATCHES = 4
#: A run estimated to take longer than this [s] is announced (warning) before it starts.
LONG_RUN_S = 600.0
#: A run estimated to take longer than this [s] (30 days) is refused: surely a typo, not a plan.
MAX_RUN_S = 30 * 86400.0

#: (energy, ledger, counts, dose-to-water sums (rows, 2, n_cells or 0): A, B of
#: :mod:`tetdose.transport.run.water`).
Rows = tuple[FloatArray, FloatArray, IntArray, FloatArray]


class TransportJob(NamedTuple):
    """Everything a batch run needs (picklable, for dask workers too)."""

    kind: str  # "mesh" | "voxel" | "hybrid"
    geom: WorldGeometry
    names: list[str | Material]  # material names (built-in) or compositions, by material index
    src: SourceArrays  # in the world's frame
    mass_g: FloatArray  # (M + V,) cell masses, mesh order then voxels [g]
    order: IntArray | None  # kernel tet i is mesh tet order[i]
    n_tets: int
    grid: ImageGrid | None
    particles: ParticleSources | None = None  # dose mode: e± beams, volume sources (src: photons)
    material_of_cell: IntArray | None = None  # (M + V,) index into names, mesh order then voxels


def assign_materials(mean_density_g_cm3: FloatArray, region: IntArray | None,
                     plan: Plan) -> tuple[IntArray, list[str]]:
    """Material index per cell and the material names used: region label → ``plan.materials``,
    any other cell its density class (:func:`tetdose.transport.physics.xs.material_for_density`)."""
    names = list(DENSITY_CLASS_MATERIALS)
    mat = material_for_density(mean_density_g_cm3).astype(np.intp)
    if plan.materials and region is None:
        warnings.warn("plan [materials] given but the geometry has no region labels; "
                      "every cell gets its density-class material", stacklevel=4)
    elif region is not None:
        for label, name in plan.materials.items():
            if name not in names:
                names.append(name)
            mat[region == label] = names.index(name)
    used, mat = np.unique(mat, return_inverse=True)
    return np.ascontiguousarray(mat.astype(np.intp)), [names[i] for i in used]


def plan_media(names: list[str], plan: Plan) -> list[str | Material]:
    """Each material name as the tables take it: the plan's ``[materials.NAME]`` composition,
    else the built-in name (checked: an unknown name is a :class:`PlanError` here)."""
    out: list[str | Material] = [plan.compositions.get(n, n) for n in names]
    for m in out:
        resolve_material(m)
    return out


def media_record(names: list[str | Material]) -> dict[str, object]:
    """Run-record entries: the material names by index and each one's composition, nominal
    density (of its density effect), I and source."""
    mats = [resolve_material(m) for m in names]
    return {"materials": [m.name for m in mats],
            "compositions": {m.name: m.record() for m in mats}}


def build_job(world: World, plan: Plan, settings: TransportSettings
              ) -> tuple[TransportJob, MeshOnGrid | None]:
    """Kernel arrays of ``world`` and the mesh-on-grid overlap pairs (hybrid worlds, else None)."""
    n_cells = ((0 if world.mesh is None else world.mesh.n_tets)
               + (0 if world.grid is None else world.grid.n_voxels))
    settings.check_tally_size(n_cells)
    arrays = world_arrays(world, lambda rho, region: assign_materials(rho, region, plan))
    grid = world.grid
    to_frame = None
    if grid is not None:
        def to_frame(a: FloatArray, is_dir: bool) -> FloatArray:
            return a @ grid.direction if is_dir else grid.to_grid_frame(a)
    n_tets = 0 if world.mesh is None else world.mesh.n_tets
    particles = None
    if settings.physics == "dose":
        points_to_frame = None if to_frame is None else (lambda a: to_frame(a, False))
        src, particles = particle_sources(
            plan, settings, to_frame,
            volume_arrays(plan.volume_sources, world, arrays, points_to_frame))
    else:
        refuse_in_kerma_mode(plan)
        src = source_arrays(plan, settings, to_frame)
    job = TransportJob(world.kind, arrays.geometry, plan_media(arrays.material_names, plan), src,
                       arrays.mass_g,
                       arrays.order, n_tets, grid, particles, arrays.material_of_cell)
    return job, arrays.on_grid


def cross_sections(job: TransportJob, settings: TransportSettings) -> CrossSections:
    """Read-only tables for ``job``, cached by name: runs with the same materials and cut-off
    (breathing phases, mesh and voxel engine) share one build."""
    return build_cross_sections(job.names, e_min_mev=min(0.01, settings.energy_cutoff_mev),
                                e_max_mev=E_MAX_MEV)


@dataclass
class Pace:
    """How many histories of each batch the next kernel call runs: adapted after every call so
    that a call lasts about ``target_s`` (the rate of the last call, at most ×8 or ÷4 at once).
    Where the batches are cut does not change a bit of the result (:mod:`._batches`)."""

    target_s: float = CALL_S
    histories: int = FIRST_CALL_HISTORIES

    def update(self, histories: int, seconds: float) -> None:
        factor = 8.0 if seconds <= 0.0 else min(8.0, max(0.25, self.target_s / seconds))
        self.histories = max(1, int(histories * factor))


def run_batches(job: TransportJob, xs: CrossSections, settings: TransportSettings,
                b_start: int, b_stop: int, pace: Pace | None = None) -> Rows:
    """Rows ``b_start … b_stop−1`` of (energy [MeV], ledger [MeV], counters, dose-to-water
    sums [MeV]: n_cells 0 unless dose mode tallies them for ``dose_to`` water), kernel cell
    order.

    ``pace``: run them in kernel calls of about ``pace.target_s`` each (so that a signal stops
    the run within about that time; bitwise the same rows); None: in one call."""
    n = b_stop - b_start
    energy = np.zeros((n, len(job.mass_g)))
    tracked = job.particles is not None and settings.dose_to == "water"
    water = np.zeros((n, 2, len(job.mass_g) if tracked else 0))
    if job.particles is not None:  # dose mode
        ledger = np.zeros((n, N_LEDGER_DOSE))
        counts = np.zeros((n, N_COUNTS_DOSE), dtype=np.int64)
        call = dose_rows_call(job, xs, settings, b_start, b_stop, energy, ledger, counts, water)
    else:
        ledger = np.zeros((n, N_LEDGER))
        counts = np.zeros((n, N_COUNTS), dtype=np.int64)

        qmc = qmc_rows(settings, b_start, b_stop)

        def call(o_from: int, o_to: int) -> None:
            run_world(*job.geom, xs, job.src, settings.seed, settings.stream,
                      settings.n_histories, settings.n_batches, b_start, b_stop, o_from, o_to,
                      qmc, settings.energy_cutoff_mev, settings.estimator == "track_length", energy,
                      ledger, counts)
    most = -(-settings.n_histories // settings.n_batches)  # histories of the largest batch
    if pace is None:
        call(0, most)
        return energy, ledger, counts, water
    done = 0
    while done < most:
        m = min(pace.histories, most - done)
        t0 = time.perf_counter()
        call(done, done + m)
        pace.update(m, time.perf_counter() - t0)
        done += m
    return energy, ledger, counts, water


def preflight(job: TransportJob, xs: CrossSections, settings: TransportSettings,
              workers: int) -> float:
    """Run the first :data:`PILOT_HISTORIES` histories (the run's own streams and physics —
    coupled photon–electron histories in dose mode, with the run's splitting — discarded): refuse
    beams that reach neither the mesh nor the CT, and warn when the whole run is estimated to
    take longer than :data:`LONG_RUN_S` on ``workers`` parallel workers (refuse it beyond
    :data:`MAX_RUN_S`). Returns the estimate [s].
    """
    n = min(settings.n_histories, PILOT_HISTORIES)
    pilot = replace(settings, n_histories=n, n_batches=2)
    tiny = replace(pilot, n_histories=2)
    run_batches(job, xs, tiny, 0, 2)  # compile / load, not timed
    t0 = time.perf_counter()
    run_batches(job, xs, tiny, 0, 2)  # the fixed cost of a call (tables, tally, thread launch)
    t1 = time.perf_counter()
    counts = run_batches(job, xs, pilot, 0, 2)[2]
    t2 = time.perf_counter()
    # per-history cost without the call's fixed cost (a pilot of 1000 cheap kerma histories is
    # otherwise mostly that), so the estimate scales with what a history costs: electrons too
    seconds = max(t2 - t1 - (t1 - t0), 0.5 * (t2 - t1)) if n > 2 else t2 - t1
    if counts[:, C_MISSED].sum() == n:
        raise PlanError(f"none of the first {n} source photons reaches the {job.kind} world: "
                        "the beams miss it; check the beams' position_mm / direction / "
                        "isocentre against the mesh and CT coordinates (mm, patient frame)")
    estimate = seconds / n * settings.n_histories / max(workers, 1)
    if estimate > MAX_RUN_S:
        raise PlanError(f"{settings.n_histories:.3g} histories would take about "
                        f"{_duration(estimate)} here ({seconds / n * 1e6:.0f} µs per history on "
                        f"{max(workers, 1)} worker(s)); give fewer --histories, or spread them "
                        "over more workers (--dask)")
    if estimate > LONG_RUN_S:
        warnings.warn(f"{settings.n_histories:.3g} histories will take about "
                      f"{_duration(estimate)} here ({seconds / n * 1e6:.0f} µs per history on "
                      f"{max(workers, 1)} worker(s)); fewer histories finish sooner",
                      stacklevel=4)
    return estimate


def _duration(seconds: float) -> str:
    for unit, size in (("days", 86400.0), ("h", 3600.0), ("min", 60.0)):
        if seconds >= size:
            return f"{seconds / size:.3g} {unit}"
    return f"{seconds:.0f} s"


def batch_histories(settings: TransportSettings) -> IntArray:
    """Histories of each batch: batch b runs histories ⌊bN/B⌋ … ⌊(b+1)N/B⌋ − 1."""
    nb = settings.n_batches
    return np.diff(np.arange(nb + 1) * settings.n_histories // nb)


def region_uncertainty(rows: list[Rows], per_batch: IntArray, target_cells: BoolArray) -> float:
    """Relative standard error of the mean dose in ``target_cells`` (kernel cell order) from the
    batch estimates x_b = E_b / n_b so far: σ/x̄ with σ² = Σ(x_b − x̄)² / (B(B − 1)) — the same
    batch statistics as :attr:`DoseResult.dose_std_gy`, for the region's energy (its mass is
    fixed, so the relative error of its dose is that of its energy). ∞ before two batches or
    while the region has no energy."""
    energy = np.concatenate([r[0][:, target_cells].sum(axis=1) for r in rows])
    b = len(energy)
    if b < 2:
        return float("inf")
    x = energy / per_batch[:b]
    mean = x.mean()
    if mean <= 0.0:
        return float("inf")
    return float(np.sqrt(((x - mean) ** 2).sum() / (b * (b - 1))) / mean)


def median_uncertainty(rows: list[Rows], per_batch: IntArray, target_cells: BoolArray) -> float:
    """Median over the cells of ``target_cells`` that have energy of each cell's relative
    standard error σ_c/x̄_c, from the batch estimates x_bc = E_bc / n_b so far (the per-cell
    statistics of :attr:`DoseResult.relative_uncertainty`). ∞ before two batches or while no
    cell has energy."""
    e = np.concatenate([r[0][:, target_cells] for r in rows])
    b = len(e)
    if b < 2:
        return float("inf")
    x = e / per_batch[:b, None]
    mean = x.mean(axis=0)
    live = mean > 0.0
    if not live.any():
        return float("inf")
    sd = np.sqrt(((x[:, live] - mean[live]) ** 2).sum(axis=0) / (b * (b - 1)))
    return float(np.median(sd / mean[live]))


def execute(job: TransportJob, on_grid: MeshOnGrid | None, plan: Plan,
            settings: TransportSettings, progress: bool | None,
            target_cells: BoolArray | None = None) -> DoseResult:
    """Check the beams reach the world and estimate the time (:func:`preflight`), run the
    batches here in groups (so the progress bar moves) and assemble the result.

    With ``settings.target_uncertainty`` and ``target_cells`` (mask over the result's cells, mesh
    order then voxels), the run stops after the first group whose :func:`region_uncertainty`
    (``target_statistic`` "mean") or :func:`median_uncertainty` ("median") reaches the target
    (at least :data:`MIN_TARGET_BATCHES` batches); the result then holds the batches run, and
    its metadata says so. More batches give a finer stop."""
    xs = cross_sections(job, settings)
    preflight(job, xs, settings, numba.get_num_threads())
    nb = settings.n_batches
    per_batch = batch_histories(settings)
    group = BATCH_GROUP_PER_THREAD * max(1, numba.get_num_threads())
    kernel_cells = None
    if settings.target_uncertainty is not None and target_cells is not None:
        kernel_cells = np.asarray(target_cells, dtype=bool).copy()
        if job.order is not None:
            kernel_cells[:job.n_tets] = kernel_cells[:job.n_tets][job.order]
    rows: list[Rows] = []
    reached = None
    measure = median_uncertainty if settings.target_statistic == "median" else region_uncertainty
    pace = Pace()
    t0, cpu0 = time.perf_counter(), time.process_time()
    with tqdm(total=nb, unit="batch", disable=None if progress is None else not progress,
              desc=f"{job.kind} transport", delay=PROGRESS_DELAY_S) as bar:
        for b0 in range(0, nb, group):
            b1 = min(nb, b0 + group)
            rows.append(run_batches(job, xs, settings, b0, b1, pace))
            bar.update(b1 - b0)
            if kernel_cells is not None and b1 >= MIN_TARGET_BATCHES and b1 < nb:
                u = measure(rows, per_batch, kernel_cells)
                bar.set_postfix_str(f"σ/D {100 * u:.2f} %")
                if u <= settings.target_uncertainty:
                    reached = b1
                    break
    extra: dict[str, object] = {"cpu_s": time.process_time() - cpu0}
    if kernel_cells is not None:
        done = reached or nb
        extra["target"] = {"uncertainty": settings.target_uncertainty,
                           "region": settings.target_region, "reached": reached is not None,
                           "statistic": settings.target_statistic,
                           "batches": done, "histories": int(per_batch[:done].sum()),
                           "achieved": measure(rows, per_batch, kernel_cells)}
        warn_target_missed(extra["target"], stacklevel=3)
    return assemble(job, on_grid, plan, settings, rows, time.perf_counter() - t0, extra,
                    per_batch=per_batch[:sum(len(r[0]) for r in rows)])


def _mix(plan: Plan) -> dict[str, object]:
    mix = source_mix(plan)
    return {} if mix is None else {"source_mix": mix}


def warn_target_missed(target: dict[str, object], stacklevel: int = 2) -> None:
    """Warn (the terminal shows it) when a run's target uncertainty (its record ``target``)
    was not reached within its histories."""
    if target["reached"]:
        return
    of = "median per-cell dose" if target.get("statistic") == "median" else "mean dose"
    warnings.warn(f"the target uncertainty {100 * float(target['uncertainty']):.3g} % of the "
                  f"{of} in {target['region']!r} was not reached: "
                  f"{100 * float(target['achieved']):.3g} % after all {target['histories']} "
                  "histories (the cap); give more --histories", stacklevel=stacklevel + 1)


def physics_record(settings: TransportSettings) -> dict[str, object]:
    """What the dose is (absorbed dose or collision kerma) and its cut-offs [MeV], for records."""
    rec: dict[str, object] = {"physics": settings.physics,
                              "photon_cutoff_mev": settings.energy_cutoff_mev}
    if settings.physics == "dose":
        rec.update(electron_cutoff_mev=settings.electron_cutoff_mev,
                   max_energy_loss_fraction=settings.max_energy_loss_fraction,
                   photon_splitting=settings.photon_splitting,
                   splitting_scheme=settings.splitting_scheme,
                   range_rejection_mev=settings.range_rejection_mev,
                   photon_tracking=settings.photon_tracking)
        if settings.secondary_photon_splitting is not None:
            rec["secondary_photon_splitting"] = settings.secondary_photon_splitting
    rec["dose_to"] = settings.dose_to
    if settings.quasi_random:
        rec["quasi_random"] = True
    return rec


def assemble(job: TransportJob, on_grid: MeshOnGrid | None, plan: Plan,
             settings: TransportSettings, rows: list[Rows], wall_s: float,
             extra: dict[str, object] | None = None, *, per_batch: IntArray | None = None
             ) -> DoseResult:
    """DoseResult from batch rows in batch order (tets moved back to mesh order); ``per_batch``:
    the histories of the rows when not all of the settings' batches ran."""
    energy = np.concatenate([r[0] for r in rows])
    sums = np.concatenate([r[3] for r in rows]).sum(axis=0)  # batch order: any thread count
    if job.order is not None:
        energy[:, job.order] = energy[:, :job.n_tets].copy()
        if sums.shape[1] > 0:
            sums[:, job.order] = sums[:, :job.n_tets].copy()
    ratio, conversion = convert(job.names, job.material_of_cell, settings, energy, sums)
    ledger = np.concatenate([r[1] for r in rows])
    counts = np.concatenate([r[2] for r in rows])
    if per_batch is None:
        per_batch = batch_histories(settings)
    result = DoseResult(energy, per_batch, job.mass_g, ledger, counts, plan.particles,
                        settings.seed, settings.estimator, job.kind, wall_s, __version__,
                        job.grid, {**media_record(job.names), "n_cells": len(job.mass_g),
                                   **physics_record(settings), **_mix(plan), **conversion,
                                   **(extra or {})},
                        n_tets=job.n_tets, on_grid=on_grid, water_ratio=ratio)
    if not np.any(energy):
        warnings.warn("the dose is zero everywhere: no photon interacted in the world (is it "
                      "vacuum, or do the beams only graze it?)", stacklevel=3)
    if result.lost_photons > 1e-4 * settings.n_histories:
        warnings.warn(f"{result.lost_photons} particles were lost in the geometry "
                      f"({result.relocations} relocations); check the mesh", stacklevel=3)
    return result
