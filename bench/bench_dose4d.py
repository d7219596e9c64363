"""Bench of a 10-phase 4D dose study on the thorax phantom: local threads vs a dask LocalCluster.

Run: ``NUMBA_CACHE_DIR=.numba-cache python bench/bench_dose4d.py [--size small|medium]
[--histories N] [--phases K] [--workers W] [--batches-per-task B]``. Prints figures; asserts
nothing. Pipeline (as ``tetdose demo``): phantom → map_density → BreathingModel series →
update_series (mass-conserving densities) → phase_densities (virtual 4D-CT) → run_dose4d with the
demo's three Co-60 fields, mesh and voxel transport per phase. Timed:

* transport per phase (mesh, voxel) and in total with numba threads in this process;
* the same with ``run_dose4d(client=…)`` on a W-worker ``LocalCluster`` (single-threaded worker
  processes; worker start-up and kernel load timed apart), and whether it is bitwise the same;
* the comparison step: both voxel accumulations (direct dose mapping, energy/mass transfer),
  energy-conserving resampling (mesh → grid, grid → mesh), gamma 3 %/3 mm inside the mesh, DVHs.
"""

from __future__ import annotations

import argparse
import os
import time
from dataclasses import replace

import numba
import numpy as np

from tetdose.compare.comparison import half_inside
from tetdose.compare.dvh import image_dvh, mesh_dvh
from tetdose.compare.gamma import gamma_index
from tetdose.core.overlap import compute_overlap
from tetdose.core.transfer import grid_dose_to_mesh, mesh_dose_to_grid
from tetdose.dose.accumulate import direct_dose_mapping, energy_mass_transfer
from tetdose.dose.dose4d import run_dose4d
from tetdose.mapping import map_density
from tetdose.motion import BreathingModel, update_series
from tetdose.motion.ct4d import phase_densities
from tetdose.phantoms import make_phantom
from tetdose.study import STRUCTURES, StudyConfig, _plan
from tetdose.transport import TransportSettings, simulate

T0 = time.perf_counter()


class Clock:
    """Named wall times [s] in the order they were taken."""

    def __init__(self) -> None:
        self.s: dict[str, float] = {}
        self.runs: dict[str, tuple] = {}  # label → (Dose4D, per-phase times, transport s, total s)

    def __call__(self, label: str, fn, *args, **kw):  # noqa: ANN001, ANN204
        t = time.perf_counter()
        out = fn(*args, **kw)
        self.s[label] = time.perf_counter() - t
        print(f"  {label}: {self.s[label]:.2f} s", flush=True)
        return out


def setup(args: argparse.Namespace, clock: Clock):  # noqa: ANN201
    ph = clock("phantom", make_phantom, "thorax", seed=1, size=args.size)
    print(f"  thorax/{args.size}: {ph.mesh.n_tets} tets, {ph.mesh.n_points} points, CT "
          f"{ph.ct.grid.size} at {ph.ct.grid.spacing_mm.tolist()} mm")
    mapped = clock("map_density (with JIT compile if the numba cache is cold)", map_density,
                   ph.mesh, ph.ct)
    series = BreathingModel(amplitude_mm=12.0).series(mapped.mesh, args.phases)
    series, _ = clock("update_series", update_series, series, mapped.density_g_cm3)
    density = clock("phase_densities (virtual 4D-CT)", phase_densities, series, ph.ct)
    tumour = {v: k for k, v in ph.label_names.items()}["tumour"]
    target = ph.mesh.centroids_mm[ph.mesh.region == tumour].mean(axis=0)
    return ph, series, density, _plan(target, StudyConfig(), tumour)


def warm_up(series, density, plan, settings: TransportSettings) -> None:  # noqa: ANN001
    tiny = replace(settings, n_histories=200, n_batches=2)
    t = time.perf_counter()
    simulate(series.mesh(0), plan, tiny, progress=False)
    simulate(density[0], plan, tiny, progress=False)
    print(f"  kernel compile/load (this process): {time.perf_counter() - t:.2f} s; threading "
          f"layer {numba.threading_layer()}")


def load() -> str:
    return f"load {os.getloadavg()[0]:.1f}"


def transport_times(run) -> dict[str, list[float]]:  # noqa: ANN001
    """Per-phase wall and CPU seconds of mesh and voxel transport (worker tasks with dask)."""
    dask = "task_s" in run.results[0].extra

    def wall(r):  # noqa: ANN001, ANN202
        return r.extra["task_s"] if dask else r.wall_s

    def cpu(r):  # noqa: ANN001, ANN202
        return r.extra["task_cpu_s" if dask else "cpu_s"]

    return {"mesh wall": [wall(r) for r in run.results],
            "mesh cpu": [cpu(r) for r in run.results],
            "voxel wall": [wall(r) for r in run.voxel.results],
            "voxel cpu": [cpu(r) for r in run.voxel.results]}


def dose4d_run(label: str, clock: Clock, *args, **kw):  # noqa: ANN001, ANN002, ANN003, ANN201
    """run_dose4d, timed; transport wall = sum of simulate calls (local) or the dask call."""
    t = time.perf_counter()
    run = run_dose4d(*args, **kw)
    total = time.perf_counter() - t
    times = transport_times(run)
    dask = "task_s" in run.results[0].extra
    transport = run.results[0].wall_s if dask else sum(times["mesh wall"] + times["voxel wall"])
    clock.runs[label] = (run, times, transport, total)
    print(f"  {label}: run_dose4d {total:.2f} s, of which transport {transport:.2f} s ({load()})",
          flush=True)
    return run


def print_runs(clock: Clock, n: int) -> None:
    print("\nper phase [s] (local: wall and process CPU of the batches of each simulate call, "
          "without job and cross-section set-up; dask: summed wall and CPU of the phase's tasks "
          "on the workers)")
    cols = [(lab, key) for lab in clock.runs for key in ("mesh wall", "mesh cpu", "voxel wall",
                                                         "voxel cpu")]
    print("| phase | " + " | ".join(f"{lab}: {key}" for lab, key in cols) + " |")
    print("|---" * (len(cols) + 1) + "|")
    for k in range(n + 1):
        row = [sum(clock.runs[lab][1][key]) if k == n else clock.runs[lab][1][key][k]
               for lab, key in cols]
        name = "sum" if k == n else f"{100 * k / n:.0f} %"
        print(f"| {name} | " + " | ".join(f"{v:.2f}" for v in row) + " |")
    print("\ntransport wall: local = sum of the batch loops; dask = the whole simulate_distributed "
          "call (job set-up, scatter, tasks, gather)")
    print("| run | transport wall s | transport CPU s | rest of run_dose4d s | run_dose4d s |")
    print("|---|---|---|---|---|")
    for lab, (_, times, transport, total) in clock.runs.items():
        cpu = sum(times["mesh cpu"] + times["voxel cpu"])
        print(f"| {lab} | {transport:.2f} | {cpu:.2f} | {total - transport:.2f} | {total:.2f} |")


def dask_run(series, density, ct, plan, settings, args, clock: Clock, reference):  # noqa: ANN001, ANN201
    from tetdose.transport.run.distributed import dask_client, simulate_distributed

    t = time.perf_counter()
    with dask_client(f"local:{args.workers}") as client:
        print(f"  LocalCluster start ({args.workers} worker processes, 1 numba thread each): "
              f"{time.perf_counter() - t:.2f} s")
        tiny = replace(settings, n_histories=400, n_batches=4 * args.workers)
        clock("dask warm-up (workers import tetdose, load kernels)", simulate_distributed,
              client, [series.mesh(0), density[0]], plan, tiny, progress=False)
        run = dose4d_run(f"dask {args.workers} workers", clock, series, plan, settings,
                         ct_hu=ct, phase_density=density, client=client,
                         batches_per_task=args.batches_per_task)
    pairs = zip(run.results + run.voxel.results, reference.results + reference.voxel.results,
                strict=True)
    same = all(np.array_equal(a.energy_per_batch_mev, b.energy_per_batch_mev) for a, b in pairs)
    same &= np.array_equal(run.accumulated.dose_gy, reference.accumulated.dose_gy)
    same &= np.array_equal(run.voxel.energy_mass_transfer.array,
                           reference.voxel.energy_mass_transfer.array)
    print(f"  bitwise identical to the local run: {'yes' if same else 'NO'}")


def comparison(ph, run, clock: Clock) -> None:  # noqa: ANN001
    series, grid = run.series, ph.ct.grid
    ref, pts, w = series.reference, series.points_mm, series.time_weight
    doses, density = run.voxel.doses, run.voxel.density
    ddm = clock("voxel accumulation: direct dose mapping", direct_dose_mapping, ref, pts, doses,
                grid, weights=w)
    emt = clock("voxel accumulation: energy/mass transfer", energy_mass_transfer, ref, pts,
                doses, density, grid, weights=w)
    acc = clock("resample mesh → grid (accumulated)", mesh_dose_to_grid, ref,
                run.accumulated.dose_gy, grid)
    clock("resample grid → mesh (phase 0 voxel dose)", grid_dose_to_mesh, series.mesh(0),
          doses[0], density_g_cm3=None)
    inside = clock("mask: voxels inside the mesh", lambda: half_inside(compute_overlap(ref, grid)))
    g = clock("gamma 3%/3mm global (inside the mesh)", gamma_index, emt, acc, mask=inside)
    print(f"    {g.n_evaluated} points, pass {g.pass_rate_percent:.1f} %")
    label_of = {name: label for label, name in ph.label_names.items()}

    def dvhs() -> int:
        n = 0
        for name in STRUCTURES:
            if name in label_of and (ref.region == label_of[name]).any():
                mask = ph.labels.array == label_of[name]
                mesh_dvh(ref, run.accumulated.dose_gy, region=label_of[name])
                image_dvh(emt, mask), image_dvh(ddm, mask)
                n += 3
        return n

    n = clock("DVHs (mesh, EMT, DDM per structure)", dvhs)
    print(f"    {n} DVHs")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--size", choices=("small", "medium"), default="small")
    p.add_argument("--histories", type=int, default=100_000, help="per phase and geometry")
    p.add_argument("--batches", type=int, default=10)
    p.add_argument("--phases", type=int, default=10)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--batches-per-task", type=int, default=1)
    args = p.parse_args()
    threads = numba.get_num_threads()
    print(f"cores {os.cpu_count()}, {load()}, numba threads {threads}")
    clock = Clock()
    print("setup")
    ph, series, density, plan = setup(args, clock)
    settings = TransportSettings(n_histories=args.histories, n_batches=args.batches, seed=1, physics="kerma")
    warm_up(series, density, plan, settings)
    print(f"\n{args.phases} phases × {args.histories} histories × (mesh + voxel), "
          f"{args.batches} batches")
    local = f"local {threads} threads"
    run = dose4d_run(local, clock, series, plan, settings, ct_hu=ph.ct, phase_density=density)
    print("\ncomparison step")
    t = time.perf_counter()
    comparison(ph, run, clock)
    compare_s = time.perf_counter() - t
    transport = clock.runs[local][2]
    print(f"  comparison total {compare_s:.2f} s (incl. both voxel accumulations) vs transport "
          f"{transport:.2f} s: {compare_s / transport:.2f}×")
    print("\ndask")
    dask_run(series, density, ph.ct, plan, settings, args, clock, run)
    print("\nlocal again (the machine's load drifts)")
    dose4d_run(f"{local}, again", clock, series, plan, settings, ct_hu=ph.ct,
               phase_density=density)
    print_runs(clock, args.phases)
    print(f"\ntotal bench time {time.perf_counter() - T0:.0f} s, {load()}")


if __name__ == "__main__":
    main()
