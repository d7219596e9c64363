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
2. **Tets and hybrid vs voxels**, and range rejection's gain (dose mode, 0.189 MeV
   electrons, 2 MeV 100 × 100 mm² field, one thread): a 300 mm water box as 30³ voxels of
   10 mm, as the structured mesh of the same box (30³ × 6 tets, every voxel cut in six), and as
   the hybrid world (the mesh of the central 150 mm cube inside the voxel box: every history
   crosses voxels → tets → voxels). Time per history (best CPU of three runs), ratio to voxels,
   electron steps, tet crossings and voxel steps per history, and the bytes a crossing and a
   step read (:data:`BYTES`).
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numba
import numpy as np

from tetdose.core.image import Image, ImageGrid
from tetdose.core.mesh import TetMesh
from tetdose.transport import PhotonSource, Plan, TransportSettings, World, simulate

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


def worlds(args: argparse.Namespace) -> None:
    numba.set_num_threads(1)
    voxels, mesh, hybrid = water_worlds()
    pl = Plan((PhotonSource("parallel", [0, 0, -150.0], [0, 0, 1], energies_mev=[2.0],
                            field_mm=[100.0, 100.0]),))
    n = int(args.world_histories)
    print(f"\n2. dose mode per history, 2 MeV 100 x 100 mm2, 300 mm water box, 1 thread, {n} "
          "histories (best CPU of 3)")
    print(f"{'world':28s} {'µs/hist':>8s} {'× voxels':>8s} {'e steps':>8s} {'tet cross':>9s} "
          f"{'vox steps':>9s}")
    base = None
    for name, geom, rr in (("voxels 30^3 (10 mm)", voxels, 0.0), ("tets 30^3 x 6", mesh, 0.0),
                           ("hybrid (15^3 x 6 tets inside)", hybrid, 0.0),
                           ("voxels, range rejection 2 MeV", voxels, 2.0),
                           ("tets, range rejection 2 MeV", mesh, 2.0),
                           ("hybrid, range rejection 2 MeV", hybrid, 2.0)):
        for cut in (0.189,):
            st = TransportSettings(n, 10, 1, physics="dose", electron_cutoff_mev=cut,
                                   range_rejection_mev=rr)
            simulate(geom, pl, TransportSettings(200, 2, physics="dose", electron_cutoff_mev=cut),
                     progress=False)
            best, rec = np.inf, {}
            for _ in range(3):
                t0 = time.process_time()
                r = simulate(geom, pl, st, progress=False)
                best = min(best, time.process_time() - t0)
                rec = r.record()
            us = best / n * 1e6
            base = base or us
            print(f"{name:28s} {us:8.1f} {us / base:8.2f} {rec['electron_steps'] / n:8.1f} "
                  f"{rec['tet_crossings'] / n:9.1f} {rec['voxel_steps'] / n:9.1f}", flush=True)
    from tetdose.transport.physics.electron_xs import build_electron_tables

    et = build_electron_tables(["water"], cutoff_mev=0.189, photon_cutoff_mev=0.01, e_max_mev=25.0)
    print("bytes read: " + ", ".join(f"{k} {v} B" for k, v in BYTES.items())
          + f"; electron tables {et.stopping.shape[2]} energies, "
          f"{6 * 2 * et.stopping.shape[2] * 8 / 1024:.0f} KiB per material")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--ompmc", type=float, default=2e4, help="ompmc histories per run")
    ap.add_argument("--tetdose", type=float, default=2e5, help="tetdose histories per run")
    ap.add_argument("--world-histories", type=float, default=2e4)
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
