"""Dose-mode efficiency against ompmc (EGSnrc physics) in one process, and tets / hybrid vs voxels.

Run: ``NUMBA_CACHE_DIR=.numba-cache .venv/bin/python bench/bench_electrons.py [--ompmc N]
[--tetdose N] [--cases a,b] [--pegs 700icru,521icru] [--split 1,4]`` (needs ``tetdose[ompmc]``
for the first part; ``--no-ompmc`` skips it).

1. **ε = 1 / (σ_rel² T)** of the dose in 1 cm³ on the axis at 95–105 mm depth (water) and at
   60–70 mm in the lung of the water / lung (0.26 g/cm³) / water slab, on the phantoms, beams and
   regions of ``bench/reference_ompmc.py`` (21 × 21 × 300 voxels of 10 × 10 × 1 mm³; 2 MeV and
   the Mohan 6 MV spectrum; 100 × 100 mm² on water, 30 × 30 mm² on the slab; tetdose's own source
   particles fed to both engines). Both engines at the same cut-offs: ``700icru`` = electrons
   0.189 MeV kinetic (AE 0.700 total), photons 0.01 MeV; ``521icru`` = 0.010 / 0.01 MeV. ompmc
   with its default photon splitting 20 (its efficient setting), tetdose with
   ``photon_splitting`` from ``--split`` (1 = analog). T is the CPU time of the run
   (``time.process_time``) with one thread each (numba ``set_num_threads(1)``, ompmc
   ``threads=1``), then the wall time with two threads each. σ from :data:`BATCHES` batches.
   Printed: µs per history, σ, ε, and ε(tetdose) / ε(ompmc).
2. **Tets and hybrid vs voxels**, photons by Woodcock tracking and by the tet walk
   (``photon_tracking``), with and without range rejection (dose mode, 0.189 MeV electrons,
   2 MeV 100 × 100 mm² field, one thread): a 300 mm water box as 30³ voxels of 10 mm, as the
   structured mesh of the same box (30³ × 6 tets, every voxel cut in six), and as the hybrid
   world (the mesh of the central 150 mm cube inside the voxel box: every history crosses
   voxels → tets → voxels). CPU per history of the transport (the batches) and of the whole
   ``simulate`` (plus the one-off world build, pilot run and result), best of three, ratios to
   voxels; the world build [s]; electron steps, tet crossings, Woodcock steps (tentative
   collisions) and voxel steps per history; then the same for the medium thorax phantom
   (:func:`thorax`: heterogeneous, one majorant for lung and bone); the point-location grid's
   size and cost per location against walking to the point; the bytes a crossing and a step
   read (:data:`BYTES`).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import replace

import numba
import numpy as np
from numba import njit

from tetdose._constants import MM_PER_CM
from tetdose.core.image import Image, ImageGrid
from tetdose.core.mesh import TetMesh
from tetdose.transport import PhotonSource, Plan, TransportSettings, World, as_world, simulate
from tetdose.transport.geometry import tets as tets_module
from tetdose.transport.geometry._tet import locate_point, walk_to
from tetdose.transport.geometry.tets import LOC_CELLS_PER_TET, mesh_geometry
from tetdose.transport.run.coupled import photon_majorant
from tetdose.transport.run.job import build_job, cross_sections, run_batches

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_transport import box  # noqa: E402
from reference_ompmc import (  # noqa: E402
    CASES,
    REGION_LUNG_MM,
    REGION_WATER_MM,
    binned,
    column_energy,
    phantom,
    plan,
)

#: Kinetic electron cut-off [MeV] of each PEGS file (AE − mc²), photon cut-off 0.01 MeV.
PEGS_CUTOFF_MEV = {"700icru": 0.189, "521icru": 0.010}
#: Bytes read from memory per cell crossed and per electron step (float64/int64 arrays):
#: a tet crossing reads planes[k] (4 × 4 × 8 = 128 B), link[k] (32 B), density[k] (32 B) and
#: material[k] (8 B); a voxel step density[v] and material[v] (16 B); an electron step reads ≈ 22
#: table entries (range at E and E(1 − f): 4, σ̂: 1, the inverse range by bisection: ≈ 12,
#: λ₁⁻¹: 2, at a hard event σ_δ, σ_brems, σ_annih: 5) = 176 B, from tables of
#: 6 × 2 × n_E × 8 B per material that stay in L1/L2 (n_E printed).
#: Batches of every run (the σ of σ is 1/√(2(B − 1)): 11 % with 40 batches, ε to ±23 %).
BATCHES = 40
BYTES = {"tet crossing": 200, "voxel step": 16, "electron step (tables)": 176}


def region_efficiency(result, grid: ImageGrid, seconds: float) -> dict[str, tuple[float, float]]:  # noqa: ANN001
    """{region: (σ_rel, ε [1/s])} of the 1 cm³ regions for a run that took ``seconds``."""
    e, m = column_energy(result, grid, slice(10, 11))
    out = {}
    for name, (lo, hi) in (("water 100 mm", REGION_WATER_MM), ("lung 60-70 mm", REGION_LUNG_MM)):
        d, sd, _ = binned(e, m, lo, hi)
        rel = sd / d
        out[name] = (rel, 1.0 / (rel * rel * seconds))
    return out


def run_engine(engine: str, case, pegs: str, n: int, threads: int, split: int,  # noqa: ANN001, ANN201
               rr_mev: float = 0.0):
    """(result, seconds): CPU seconds with one thread, wall seconds with more."""
    rho, lab = phantom(case.slab)
    cut = PEGS_CUTOFF_MEV[pegs]
    st = TransportSettings(n, BATCHES, 1, physics="dose", electron_cutoff_mev=cut,
                           photon_splitting=split, range_rejection_mev=rr_mev)
    numba.set_num_threads(threads)
    if engine == "ompmc":
        from tetdose.coupling.ompmc import OmpmcOptions, simulate_ompmc

        opts = OmpmcOptions(pegs=pegs, electron_cutoff_mev=cut, threads=threads)

        def call(s: TransportSettings):  # noqa: ANN202
            return simulate_ompmc(rho, plan(case), s, labels=lab, progress=False, options=opts)
    else:
        def call(s: TransportSettings):  # noqa: ANN202
            return simulate(rho, plan(case), s, labels=lab, progress=False)
    call(TransportSettings(20, 2, 7, physics="dose", electron_cutoff_mev=cut,
                           photon_splitting=split))  # warm-up
    t0, c0 = time.perf_counter(), time.process_time()
    r = call(st)
    seconds = time.process_time() - c0 if threads == 1 else time.perf_counter() - t0
    return r, seconds


def efficiency(args: argparse.Namespace) -> None:
    print("1. ε = 1/(σ²T) of 1 cm³, tetdose voxels vs ompmc (split 20), same phantom/beam/cut-offs")
    print(f"{'case':16s} {'pegs':8s} {'thr':>3s} {'engine':14s} {'µs/hist':>8s} "
          f"{'region':14s} {'σ %':>6s} {'ε 1/s':>9s} {'ratio':>6s}")
    for case in CASES:
        if case.name not in args.cases.split(","):
            continue
        rho, _ = phantom(case.slab)
        for pegs in args.pegs.split(","):
            for threads in (int(t) for t in args.threads.split(",")):
                runs = []
                if not args.no_ompmc:
                    runs.append(("ompmc", "ompmc", args.ompmc, 20, 0.0))
                runs += [(f"tetdose s{s}", "tetdose", args.tetdose, s, 0.0)
                         for s in (int(x) for x in args.split.split(","))]
                runs += [(f"tetdose rr{rr:g}", "tetdose", args.tetdose, 1, rr)
                         for rr in (float(x) for x in args.rr.split(",") if x)]
                base = {}
                for label, engine, n, split, rr in runs:
                    r, sec = run_engine(engine, case, pegs, int(n), threads, split, rr)
                    eff = region_efficiency(r, rho.grid, sec)
                    for region, (rel, eps) in eff.items():
                        if region.startswith("lung") and not case.slab:
                            continue
                        base.setdefault(region, eps)
                        print(f"{case.name:16s} {pegs:8s} {threads:3d} {label:14s} "
                              f"{sec / int(n) * 1e6:8.1f} {region:14s} {rel * 100:6.2f} "
                              f"{eps:9.3g} {eps / base[region]:6.2f}", flush=True)
    numba.set_num_threads(1)


def water_worlds(n: int = 30, size_mm: float = 300.0):  # noqa: ANN201
    """(voxel image, mesh of the box, hybrid world: mesh of the central cube inside the voxels)."""
    mesh, _ = box(n, size_mm)
    mesh = TetMesh(mesh.points_mm, mesh.tets, np.ones(mesh.n_tets, int),
                   {"density": np.ones(mesh.n_points)})
    spacing = np.full(3, size_mm / n)
    grid = ImageGrid(spacing / 2 - size_mm / 2, spacing, np.eye(3), (n, n, n))
    voxels = Image(np.ones(grid.shape), grid)
    inner, _ = box(n // 2, size_mm / 2)
    inner = TetMesh(inner.points_mm, inner.tets, np.ones(inner.n_tets, int),
                    {"density": np.ones(inner.n_points)})
    return voxels, mesh, World(mesh=inner, density=voxels)


def transport_times(geom, pl: Plan, st: TransportSettings):  # noqa: ANN001, ANN201
    """(world build [s], transport [µs/photon], simulate [µs/photon], record): CPU seconds, best
    of three. The build (kernel arrays, boundary lists, point-location grid) is done once per
    world; the transport is every batch of the run (``run_batches``); simulate is both plus the
    pilot run and the result."""
    world = as_world(geom, None)
    n = st.n_histories
    simulate(world, pl, replace(st, n_histories=200, n_batches=2), progress=False)  # compile
    build = run = total = np.inf
    rec: dict = {}
    for _ in range(3):
        t0 = time.process_time()
        job, _ = build_job(world, pl, st)
        build = min(build, time.process_time() - t0)
        xs = cross_sections(job, st)
        t0 = time.process_time()
        run_batches(job, xs, st, 0, st.n_batches)
        run = min(run, time.process_time() - t0)
        t0 = time.process_time()
        r = simulate(world, pl, st, progress=False)
        total = min(total, time.process_time() - t0)
        rec = r.record()
    return build, run / n * 1e6, total / n * 1e6, rec


@njit(cache=True)
def _locate_all(g, starts, ends, ks, by_walk):  # noqa: ANN001, ANN202
    """Tets holding ``ends`` (sum of ids, a checksum): by the point-location grid, or by walking
    from the tet ``ks`` holding ``starts`` along the segment (the alternative to the grid)."""
    total = 0
    for n in range(len(ends)):
        if by_walk:
            dx, dy, dz = ends[n, 0] - starts[n, 0], ends[n, 1] - starts[n, 1], ends[n, 2] - starts[n, 2]
            length = np.sqrt(dx * dx + dy * dy + dz * dz)
            k, _ = walk_to(g, ks[n], starts[n, 0], starts[n, 1], starts[n, 2], dx / length,
                           dy / length, dz / length, length)
        else:
            k = locate_point(g, ends[n, 0], ends[n, 1], ends[n, 2])
        total += k
    return total


def point_location(mesh: TetMesh, mean_mm: float, n: int = 200_000) -> None:
    """ns per point location in ``mesh`` of the end of a segment of exponential length (mean
    ``mean_mm``, a photon's mean free path under the majorant) from a random point inside: the
    grid vs the walk from the start's tet, for each grid size."""
    rng = np.random.default_rng(1)
    lo, hi = mesh.points_mm.min(axis=0), mesh.points_mm.max(axis=0)
    starts = rng.uniform(lo, hi, (n, 3))
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    ends = starts + rng.exponential(mean_mm, (n, 1)) * d
    inside = np.all((ends > lo) & (ends < hi), axis=1)  # the box is convex: the walk stays in
    starts, ends = starts[inside], ends[inside]
    for cells_per_tet in (0.5, 1.0, 2.0, 4.0):
        tets_module.LOC_CELLS_PER_TET = cells_per_tet
        g = mesh_geometry(mesh, np.ones(mesh.n_points), np.zeros(mesh.n_tets, np.intp))
        ks = _start_tets(g, starts)
        res = {}
        for by_walk in (False, True):
            if by_walk and cells_per_tet != 1.0:
                continue
            _locate_all(g, starts[:10], ends[:10], ks[:10], by_walk)
            t0 = time.perf_counter()
            _locate_all(g, starts, ends, ks, by_walk)
            res["walk" if by_walk else "grid"] = (time.perf_counter() - t0) / len(ends) * 1e9
        mib = (g.loc_start.nbytes + g.loc_items.nbytes) / 2**20
        print(f"  {cells_per_tet:3g} cells/tet ({'x'.join(map(str, g.loc_n))}): grid "
              f"{res['grid']:6.0f} ns, {np.diff(g.loc_start).mean():4.1f} tets/cell, "
              f"{mib:5.1f} MiB" + (f"; walk from the start's tet {res['walk']:6.0f} ns"
                                   if "walk" in res else ""), flush=True)
    tets_module.LOC_CELLS_PER_TET = LOC_CELLS_PER_TET


@njit(cache=True)
def _start_tets(g, starts):  # noqa: ANN001, ANN202
    out = np.empty(len(starts), dtype=np.intp)
    for n in range(len(starts)):
        out[n] = locate_point(g, starts[n, 0], starts[n, 1], starts[n, 2])
    return out


def thorax(n: int) -> None:
    """The medium thorax phantom (Schneider densities, labels → materials): its CT alone, the
    hybrid world (its organ mesh, vertex densities mapped from the CT, inside the CT) and the mesh
    alone, 2 MeV 60 × 60 mm² from the front, Woodcock and walk: a heterogeneous case where one
    majorant (the bone's, ρ_max up to 1.6 g/cm³) covers lung too."""
    from tetdose.core.calibration import HUCalibration
    from tetdose.mapping import map_density
    from tetdose.phantoms import make_phantom

    ph = make_phantom("thorax", seed=0, size="medium")
    cal = HUCalibration.schneider2000()
    rho = Image(cal(ph.ct.array), ph.ct.grid)
    mesh = map_density(ph.mesh, ph.ct, calibration=cal).mesh
    c = mesh.centroids_mm.mean(axis=0)
    pl = Plan((PhotonSource("parallel", [c[0], c[1] - 300.0, c[2]], [0, 1, 0],
                            energies_mev=[2.0], field_mm=[60.0, 60.0]),), materials=ph.materials)
    print(f"thorax phantom (medium): {mesh.n_tets} tets, CT {'x'.join(map(str, rho.grid.size))}")
    base = None
    for name, world in (("CT voxels", World(density=rho, labels=ph.labels)),
                        ("hybrid", World(mesh=mesh, density=rho, labels=ph.labels)),
                        ("mesh alone", World(mesh=mesh))):
        for tracking in ("woodcock", "walk"):
            if name == "CT voxels" and tracking == "walk":
                continue
            st = TransportSettings(n, 10, 1, physics="dose", electron_cutoff_mev=0.189,
                                   photon_tracking=tracking)
            build, us, us_sim, rec = transport_times(world, pl, st)
            base = base or (us, us_sim)
            label = "-" if name == "CT voxels" else tracking
            print(f"{name:24s} {label:9s} {'':3s} {build:7.2f} {us:8.2f} {us / base[0]:6.2f} "
                  f"{us_sim:8.1f} {us_sim / base[1]:6.2f} {rec['electron_steps'] / n:7.1f} "
                  f"{rec['tet_crossings'] / n:9.1f} {rec['woodcock_steps'] / n:7.2f} "
                  f"{rec['voxel_steps'] / n:9.1f}", flush=True)


def worlds(args: argparse.Namespace) -> None:
    numba.set_num_threads(1)
    voxels, mesh, hybrid = water_worlds()
    pl = Plan((PhotonSource("parallel", [0, 0, -150.0], [0, 0, 1], energies_mev=[2.0],
                            field_mm=[100.0, 100.0]),))
    n = int(args.world_histories)
    print(f"\n2. dose mode per history, 2 MeV 100 x 100 mm2, 300 mm water box, 1 thread, {n} "
          "histories (CPU, best of 3): transport = the batches, simulate = + world build, "
          "pilot, result")
    print(f"{'world':24s} {'photons':9s} {'rr':>3s} {'build s':>7s} {'µs/hist':>8s} "
          f"{'× vox':>6s} {'simulate':>8s} {'× vox':>6s} {'e steps':>7s} {'tet cross':>9s} "
          f"{'wood st':>7s} {'vox steps':>9s}")
    base: dict[float, tuple[float, float]] = {}
    for rr in (0.0, 2.0):
        for name, geom in (("voxels 30^3 (10 mm)", voxels), ("tets 30^3 x 6", mesh),
                           ("hybrid (15^3 x 6 inside)", hybrid)):
            for tracking in ("woodcock", "walk"):
                if name.startswith("voxels") and tracking == "walk":
                    continue
                st = TransportSettings(n, 10, 1, physics="dose", electron_cutoff_mev=0.189,
                                       range_rejection_mev=rr, photon_tracking=tracking)
                build, us, us_sim, rec = transport_times(geom, pl, st)
                b_run, b_sim = base.setdefault(rr, (us, us_sim))
                label = "-" if name.startswith("voxels") else tracking
                print(f"{name:24s} {label:9s} {rr:3g} {build:7.2f} {us:8.2f} {us / b_run:6.2f} "
                      f"{us_sim:8.1f} {us_sim / b_sim:6.2f} {rec['electron_steps'] / n:7.1f} "
                      f"{rec['tet_crossings'] / n:9.1f} {rec['woodcock_steps'] / n:7.2f} "
                      f"{rec['voxel_steps'] / n:9.1f}", flush=True)
    thorax(n)
    g = World(mesh=mesh)
    job, _ = build_job(g, pl, TransportSettings(10, 2))
    t = job.geom.tet
    per_cell = np.diff(t.loc_start)
    grid_bytes = t.loc_start.nbytes + t.loc_items.nbytes
    print(f"point-location grid of the {mesh.n_tets} tets: {'x'.join(map(str, t.loc_n))} cells, "
          f"{per_cell.mean():.1f} tets listed per cell (max {per_cell.max()}), "
          f"{grid_bytes / 2**20:.1f} MiB ({grid_bytes / mesh.n_tets:.0f} B per tet; planes "
          f"{t.planes.nbytes / mesh.n_tets:.0f} B per tet)")
    xs = cross_sections(job, TransportSettings(10, 2))
    hat = photon_majorant(xs, t.rho_max)
    x = (np.log(2.0) - xs.ln_e_min) / xs.d_ln_e
    i = int(x)
    mfp_mm = MM_PER_CM / np.exp(hat[i] + (x - i) * (hat[i + 1] - hat[i]))
    print(f"point location at the end of a 2 MeV majorant free path ({mfp_mm:.0f} mm), 1 thread:")
    point_location(mesh, mfp_mm)
    from tetdose.transport.physics.electron_xs import build_electron_tables

    et = build_electron_tables(["water"], cutoff_mev=0.189, photon_cutoff_mev=0.01, e_max_mev=25.0)
    print("bytes read: " + ", ".join(f"{k} {v} B" for k, v in BYTES.items())
          + f"; electron tables {et.stopping.shape[2]} energies, "
          f"{6 * 2 * et.stopping.shape[2] * 8 / 1024:.0f} KiB per material")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--ompmc", type=float, default=2e4, help="ompmc histories per run")
    ap.add_argument("--tetdose", type=float, default=2e5, help="tetdose histories per run")
    ap.add_argument("--world-histories", type=float, default=4e5)
    ap.add_argument("--cases", default="water_2MeV_100,water_6MV_100,slab_2MeV_30")
    ap.add_argument("--pegs", default="700icru")
    ap.add_argument("--split", default="1")
    ap.add_argument("--rr", default="", help="range rejection energies [MeV] to add, e.g. 2")
    ap.add_argument("--threads", default="1,2")
    ap.add_argument("--no-ompmc", action="store_true")
    ap.add_argument("--no-worlds", action="store_true")
    ap.add_argument("--no-efficiency", action="store_true")
    args = ap.parse_args()
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    if not args.no_efficiency:
        efficiency(args)
    if not args.no_worlds:
        worlds(args)


if __name__ == "__main__":
    main()
