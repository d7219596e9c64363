"""ompmc reference curves for the electron-transport tests (issue 19) and its efficiency (issue 20).

Run: ``NUMBA_CACHE_DIR=.numba-cache .venv/bin/python bench/reference_ompmc.py [--histories N]
[--cases a,b] [--out DIR]`` (needs ``tetdose[ompmc]``). In one run, for every case of
:data:`CASES` — water, 2 MeV and the Mohan 6 MV spectrum (``"6MV"``, tetdose's lines), 100 × 100
and 30 × 30 mm² parallel fields; and a water / lung (0.26 g/cm³) / water slab (lung 30–100 mm)
with a 30 × 30 mm² field — it computes with :func:`tetdose.coupling.ompmc.simulate_ompmc` (EGSnrc
physics, 10 keV electron and photon cut-offs, ompmc's photon splitting 20; tetdose's own source
particles):

- the central-axis depth dose [Gy per source photon] in the column :data:`COLUMN_VOXELS` around
  the axis (the phantom's voxels are 10 × 10 × 1 mm³; 1 mm depth bins to 30 mm, 5 mm beyond),
  with its standard deviation from the batches, beside tetdose's collision kerma (its own engine,
  track length, ten times the histories) on the same phantom and column;
- the time per history on one core (a pilot of ``--pilot`` histories with one OpenMP thread) and
  with two threads (the whole run);
- the efficiency ε = 1 / (σ_rel² T) of the dose in 1 cm³ on the axis (10 × 10 mm² × 10 mm) at
  100 mm depth in water and at 60–70 mm in the lung, with T the time the run took on one core
  (N · t₁) and with two threads (wall).

Writes ``OUT/<case>.csv`` (depth_lo_mm, depth_hi_mm, dose_gy, dose_std_gy, kerma_gy, kerma_std_gy)
and ``OUT/<case>.npz`` (the 1 mm bins and the full per-batch column energies) and
``OUT/summary.json``; OUT defaults to ``bench/out/reference_ompmc`` (git-ignored). The figures
depend on the machine's load (printed): run it on a quiet machine for the efficiency figures.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path
from typing import Any, NamedTuple

import numba
import numpy as np

from tetdose._constants import J_PER_MEV
from tetdose.core.image import Image, ImageGrid
from tetdose.coupling.ompmc import OmpmcOptions, simulate_ompmc
from tetdose.plan.model import Plan
from tetdose.plan.photon_source import PhotonSource
from tetdose.plan.spectra import named_spectrum
from tetdose.transport import simulate
from tetdose.transport.history.result import DoseResult
from tetdose.transport.run.settings import TransportSettings

OUT = Path(__file__).resolve().parent / "out" / "reference_ompmc"
#: Phantom: 21 × 21 lateral voxels of 10 mm (the axis through the middle of voxel 10), depth 1 mm
#: voxels to DEPTH_MM.
LATERAL_MM, N_LATERAL, DEPTH_MM = 10.0, 21, 300
#: Central-axis column (lateral voxel range) per field size [mm]: ±5 mm for 30 mm, ±15 mm for 100.
COLUMN_VOXELS = {30.0: slice(10, 11), 100.0: slice(9, 12)}
#: 1 mm bins to this depth [mm], then 5 mm bins.
FINE_TO_MM, COARSE_MM = 30, 5
#: Lung slab of the slab phantom [mm] (water before and after).
LUNG_MM = (30, 100)
LUNG_G_CM3 = 0.26
#: 1 cm³ scoring regions on the axis (depth range [mm]) for the efficiency.
REGION_WATER_MM = (95, 105)
REGION_LUNG_MM = (60, 70)


class Case(NamedTuple):
    name: str
    beam: str  # "2MeV" | "6MV"
    field_mm: float
    slab: bool


CASES = (Case("water_2MeV_100", "2MeV", 100.0, False), Case("water_2MeV_30", "2MeV", 30.0, False),
         Case("water_6MV_100", "6MV", 100.0, False), Case("water_6MV_30", "6MV", 30.0, False),
         Case("slab_2MeV_30", "2MeV", 30.0, True), Case("slab_6MV_30", "6MV", 30.0, True))


def phantom(slab: bool) -> tuple[Image, Image]:
    """(density [g/cm³], labels: 1 water, 2 lung) of the water or water/lung/water phantom."""
    half = N_LATERAL * LATERAL_MM / 2
    grid = ImageGrid([-half + LATERAL_MM / 2, -half + LATERAL_MM / 2, 0.5],
                     [LATERAL_MM, LATERAL_MM, 1.0], np.eye(3), (N_LATERAL, N_LATERAL, DEPTH_MM))
    depth = np.arange(DEPTH_MM) + 0.5
    lung = (depth > LUNG_MM[0]) & (depth < LUNG_MM[1]) if slab else np.zeros(DEPTH_MM, bool)
    rho = np.where(lung, LUNG_G_CM3, 1.0)[:, None, None] * np.ones(grid.shape)
    lab = np.where(lung, 2, 1)[:, None, None] * np.ones(grid.shape, dtype=np.int32)
    return Image(rho, grid), Image(lab.astype(np.int32), grid)


def plan(case: Case) -> Plan:
    energies, weights = (np.array([2.0]), np.ones(1)) if case.beam == "2MeV" else \
        named_spectrum(case.beam)
    src = PhotonSource("parallel", [0.0, 0.0, -50.0], [0, 0, 1], energies_mev=energies,
                       line_weights=weights, field_mm=[case.field_mm, case.field_mm])
    return Plan((src,), materials={1: "water", 2: "lung"})


def column_energy(result: DoseResult, grid: ImageGrid, cols: slice) -> tuple[np.ndarray, np.ndarray]:
    """(per-batch energy per history in the column by 1 mm depth voxel (B, nz) [MeV], column
    mass per depth voxel (nz,) [g])."""
    e = result.energy_per_batch_mev.reshape(-1, *grid.shape)[:, :, cols, cols].sum(axis=(2, 3))
    return e / result.histories_per_batch[:, None], \
        result.mass_g.reshape(grid.shape)[:, cols, cols].sum(axis=(1, 2))


def bins() -> list[tuple[int, int]]:
    return [(z, z + 1) for z in range(FINE_TO_MM)] + \
        [(z, z + COARSE_MM) for z in range(FINE_TO_MM, DEPTH_MM, COARSE_MM)]


def binned(e: np.ndarray, m: np.ndarray, lo: int, hi: int) -> tuple[float, float, np.ndarray]:
    """(dose [Gy], σ [Gy], per-batch dose) of depth bin [lo, hi) mm (1 mm voxel z = depth)."""
    per_batch = e[:, lo:hi].sum(axis=1) / m[lo:hi].sum() * J_PER_MEV * 1000.0
    return float(per_batch.mean()), float(per_batch.std(ddof=1) / np.sqrt(len(per_batch))), \
        per_batch


def run_case(case: Case, n: int, pilot: int, out: Path) -> dict[str, Any]:
    rho, lab = phantom(case.slab)
    grid, pl, cols = rho.grid, plan(case), COLUMN_VOXELS[case.field_mm]
    # OmpmcOptions defaults: 521icru (10 keV electrons), 10 keV photons (the settings'), split 20
    t0 = time.process_time()
    one = simulate_ompmc(rho, pl, TransportSettings(pilot, 2, 99), labels=lab, progress=False,
                         options=OmpmcOptions(threads=1))
    t1 = (time.process_time() - t0) / pilot
    res = simulate_ompmc(rho, pl, TransportSettings(n, 10, 1), labels=lab, progress=False,
                         options=OmpmcOptions(threads=2))
    t2 = res.wall_s / n
    kerma = simulate(rho, pl, TransportSettings(10 * n, 10, 1), labels=lab, progress=False)
    e_d, m = column_energy(res, grid, cols)
    e_k, _ = column_energy(kerma, grid, cols)
    rows = []
    for lo, hi in bins():
        d, sd, _ = binned(e_d, m, lo, hi)
        k, sk, _ = binned(e_k, m, lo, hi)
        rows.append((lo, hi, d, sd, k, sk))
    out.mkdir(parents=True, exist_ok=True)
    with open(out / f"{case.name}.csv", "w") as f:
        f.write("depth_lo_mm,depth_hi_mm,dose_gy,dose_std_gy,kerma_gy,kerma_std_gy\n")
        for r in rows:
            f.write(",".join(f"{v:.6g}" for v in r) + "\n")
    np.savez_compressed(out / f"{case.name}.npz", column_energy_mev=e_d, column_mass_g=m,
                        kerma_column_energy_mev=e_k)
    info: dict[str, Any] = {
        "histories": n, "us_per_history_1_core": t1 * 1e6, "us_per_history_2_threads_wall":
            t2 * 1e6, "pilot_histories": pilot, "column_mm": (cols.stop - cols.start) * LATERAL_MM,
        "media": res.extra["media"], "ledger": res.ledger, "kerma_ledger": kerma.ledger,
        "load_average": os.getloadavg()[0], "one_thread_run_s": one.wall_s}
    regions = {"water_100mm": REGION_WATER_MM} | ({"lung_60_70mm": REGION_LUNG_MM} if case.slab
                                                  else {})
    full = slice(10, 11)  # the 1 cm³ region: the central 10 × 10 mm² voxel column
    e_r, m_r = column_energy(res, grid, full)
    for name, (lo, hi) in regions.items():
        d, sd, _ = binned(e_r, m_r, lo, hi)
        rel2 = (sd / d) ** 2
        info[name] = {"dose_gy": d, "rel_std": sd / d,
                      "efficiency_1_core_per_s": 1.0 / (rel2 * n * t1),
                      "efficiency_2_threads_per_s": 1.0 / (rel2 * n * t2)}
    return info


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--histories", type=float, default=1e5, help="per case (default 1e5)")
    ap.add_argument("--pilot", type=int, default=5000,
                    help="histories of the one-thread timing run per case")
    ap.add_argument("--cases", default=",".join(c.name for c in CASES))
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args()
    wanted = args.cases.split(",")
    summary: dict[str, Any] = {"numba_threads": numba.get_num_threads(), "cases": {}}
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    for case in CASES:
        if case.name not in wanted:
            continue
        t = time.perf_counter()
        info = run_case(case, int(args.histories), args.pilot, args.out)
        summary["cases"][case.name] = info
        eff = "; ".join(f"{k}: σ {v['rel_std'] * 100:.2f} %, ε₁ {v['efficiency_1_core_per_s']:.3g}/s, "
                        f"ε₂ {v['efficiency_2_threads_per_s']:.3g}/s"
                        for k, v in info.items() if isinstance(v, dict) and "rel_std" in v)
        print(f"{case.name}: {info['us_per_history_1_core']:.0f} µs/history on 1 core, "
              f"{info['us_per_history_2_threads_wall']:.0f} µs wall on 2 threads; {eff} "
              f"({time.perf_counter() - t:.0f} s, load {info['load_average']:.1f})", flush=True)
        (args.out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    print(f"→ {args.out}")


if __name__ == "__main__":
    main()
