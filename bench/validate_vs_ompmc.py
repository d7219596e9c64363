"""tetdose's dose mode against ompmc (EGSnrc physics) on the phantoms of ``reference_ompmc.py`` (issue 19).

Run: ``NUMBA_CACHE_DIR=.numba-cache .venv/bin/python bench/validate_vs_ompmc.py [--histories N]
[--cases a,b] [--cutoffs 0.01,0.2] [--ref DIR]``. The ompmc curves come from
``bench/reference_ompmc.py`` (its CSVs in ``--ref``, default ``bench/out/reference_ompmc``: run
that first; 10 keV electron and photon cut-offs, 521icru). For each case and electron cut-off
tetdose runs the same phantom (21 × 21 lateral voxels of 10 mm, 1 mm deep), the same source and the
same central-axis column, photon cut-off 10 keV, and prints per depth bin its dose and ompmc's
divided by the collision kerma (tetdose track length, the reference's column), with σ, and the
issue-19 criteria:

- build-up (surface to d_max): max |D_t − D_o| / D_max ≤ 3 %;
- beyond 2 mm depth: each bin within 2 % of the local dose or 1 mm (the dose ompmc has within
  ±1 mm of the bin's centre, linear interpolation between bin centres);
- in the lung (slab cases, 35–95 mm): the mean dose within 1 %.

Each criterion's worst value is printed with the statistical noise of the difference (σ of both
runs): a difference within its tolerance plus 2–3 σ is not resolved by the run. Also the CPU time per history
(``time.process_time``, both threads). Writes ``bench/out/validate_<case>_<cutoff>.csv``;
``--tradeoff`` then prints the electron cut-off table of bench/README.md from those files
(``--cases water_2MeV_100,slab_6MV_30 --cutoffs 0.01,0.05,0.1,0.2,0.5``).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numba
import numpy as np

from tetdose.transport import simulate
from tetdose.transport.run.settings import TransportSettings

sys.path.insert(0, str(Path(__file__).resolve().parent))
from reference_ompmc import CASES, COLUMN_VOXELS, LUNG_MM, OUT, binned, bins, column_energy, phantom, plan  # noqa: E402,E501

#: Lung depths [mm] of the 1 % criterion (5 mm from each interface: the lateral-equilibrium
#: region of a 30 mm field in 0.26 g/cm³ lung is not reached, the criterion compares codes).
LUNG_SCORE_MM = (LUNG_MM[0] + 5, LUNG_MM[1] - 5)


def run_tetdose(case, n: int, cutoff_mev: float, seed: int = 1):  # noqa: ANN001, ANN201
    """(per-bin dose [Gy], σ [Gy], CPU s per history) of tetdose on the reference's phantom."""
    rho, lab = phantom(case.slab)
    settings = TransportSettings(n, 10, seed, energy_cutoff_mev=0.01, electron_cutoff_mev=cutoff_mev)
    t0 = time.process_time()
    res = simulate(rho, plan(case), settings, labels=lab, progress=False)
    cpu = (time.process_time() - t0) / n
    e, m = column_energy(res, rho.grid, COLUMN_VOXELS[case.field_mm])
    d = np.array([binned(e, m, lo, hi)[:2] for lo, hi in bins()])
    return d[:, 0], d[:, 1], cpu, res.wall_s / n


def compare(ref: np.ndarray, dose: np.ndarray, sd: np.ndarray, slab: bool) -> dict[str, float]:
    """Issue-19 criteria of tetdose's (dose, sd) against ompmc's reference rows."""
    lo, hi = ref["depth_lo_mm"], ref["depth_hi_mm"]
    mid = 0.5 * (lo + hi)
    d_o, s_o = ref["dose_gy"], ref["dose_std_gy"]
    fine = hi - lo == 1
    i_max = int(np.argmax(np.where(fine & (mid < 40), d_o, 0.0)))
    d_max = d_o[i_max]
    build = slice(0, i_max + 1)
    diff = dose - d_o
    s_diff = np.hypot(sd, s_o)
    out = {"buildup_max_pct": float(np.max(np.abs(diff[build])) / d_max * 100),
           "buildup_sigma_pct": float(np.max(s_diff[build]) / d_max * 100)}
    # 2 % / 1 mm beyond 2 mm: the smallest of the local % difference and the % difference to the
    # ompmc dose anywhere within ±1 mm (interpolated between bin centres)
    deep = (lo >= 2) & ~(slab & (mid > LUNG_MM[0] - 3) & (mid < LUNG_MM[0] + 3)) | (lo >= 2) & ~slab
    worst, worst_sigma = 0.0, 0.0
    for i in np.flatnonzero(deep):
        shifts = np.interp(mid[i] + np.linspace(-1, 1, 21), mid, d_o)
        err = np.min(np.abs(dose[i] - shifts)) / d_o[i] * 100
        if err > worst:
            worst, worst_sigma = err, s_diff[i] / d_o[i] * 100
    out["beyond2mm_worst_pct"], out["beyond2mm_sigma_pct"] = float(worst), float(worst_sigma)
    if slab:
        lung = (lo >= LUNG_SCORE_MM[0]) & (hi <= LUNG_SCORE_MM[1])
        w = hi[lung] - lo[lung]
        t, o = np.sum(dose[lung] * w), np.sum(d_o[lung] * w)
        s = np.hypot(np.sqrt(np.sum((sd[lung] * w) ** 2)), np.sqrt(np.sum((s_o[lung] * w) ** 2)))
        out["lung_mean_pct"], out["lung_sigma_pct"] = float((t / o - 1) * 100), float(s / o * 100)
    return out


#: Regions of the cut-off trade-off table: (name, from mm, to mm).
TRADEOFF_REGIONS = (("0-1 mm", 0, 1), ("0-3 mm", 0, 3), ("3-6 mm", 3, 6), ("10-30 mm", 10, 30))


def tradeoff(case: str, cutoffs: list[str], ref_dir: Path) -> None:
    """Print the depth-dose in a few regions (÷ ompmc's dose at 8–30 mm) for ompmc (10 keV) and
    every tetdose cut-off saved by earlier runs of this script (``OUT.parent``), with σ."""
    ref = np.genfromtxt(ref_dir / f"{case}.csv", delimiter=",", names=True)
    lo, hi = ref["depth_lo_mm"], ref["depth_hi_mm"]

    def agg(d: np.ndarray, s: np.ndarray, a: float, b: float) -> tuple[float, float]:
        m = (lo >= a) & (hi <= b)
        w = hi[m] - lo[m]
        return float(np.sum(d[m] * w) / w.sum()), float(np.sqrt(np.sum((s[m] * w) ** 2)) / w.sum())

    regions = TRADEOFF_REGIONS + ((("lung 35-95 mm", *LUNG_SCORE_MM),) if "slab" in case
                                  else (("50-100 mm", 50, 100),))
    d_ref = agg(ref["dose_gy"], ref["dose_std_gy"], 8, 30)[0]
    rows = {"ompmc 0.01": (ref["dose_gy"], ref["dose_std_gy"])}
    for c in cutoffs:
        path = OUT.parent / f"validate_{case}_{c}.csv"
        if path.exists():
            a = np.loadtxt(path, delimiter=",")
            rows[f"tetdose {c}"] = (a[:, 2], a[:, 3])
    print(f"\n{case}: dose ÷ ompmc's mean dose at 8–30 mm, ± σ")
    print("| cut-off [MeV] | " + " | ".join(r[0] for r in regions) + " |")
    for name, (d, s) in rows.items():
        cells = [agg(d, s, a, b) for _, a, b in regions]
        print(f"| {name} | " + " | ".join(f"{v / d_ref:.3f} ± {e / d_ref:.3f}" for v, e in cells)
              + " |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--histories", type=float, default=2e6)
    ap.add_argument("--cases", default=",".join(c.name for c in CASES))
    ap.add_argument("--cutoffs", default="0.01")
    ap.add_argument("--ref", type=Path, default=OUT)
    ap.add_argument("--rows", type=int, default=16, help="depth bins printed per case")
    ap.add_argument("--tradeoff", action="store_true",
                    help="only print the cut-off table of the runs saved before")
    args = ap.parse_args()
    if args.tradeoff:
        for name in args.cases.split(","):
            tradeoff(name, args.cutoffs.split(","), args.ref)
        return
    print(f"numba threads {numba.get_num_threads()}")
    for case in CASES:
        if case.name not in args.cases.split(","):
            continue
        ref = np.genfromtxt(args.ref / f"{case.name}.csv", delimiter=",", names=True)
        k = ref["kerma_gy"]
        for cut in (float(c) for c in args.cutoffs.split(",")):
            dose, sd, cpu, wall = run_tetdose(case, int(args.histories), cut)
            crit = compare(ref, dose, sd, case.slab)
            print(f"\n{case.name}, electron cut-off {cut} MeV: {cpu * 1e6:.1f} µs CPU/history "
                  f"({wall * 1e6:.1f} µs wall)")
            print("  depth mm   tetdose D/K      ompmc D/K")
            for i in range(min(args.rows, len(ref))):
                print(f"  {ref['depth_lo_mm'][i]:3.0f}-{ref['depth_hi_mm'][i]:3.0f}  "
                      f"{dose[i] / k[i]:.3f} ± {sd[i] / k[i]:.3f}   "
                      f"{ref['dose_gy'][i] / k[i]:.3f} ± {ref['dose_std_gy'][i] / k[i]:.3f}")
            print("  " + ", ".join(f"{n} {v:.2f}" for n, v in crit.items()), flush=True)
            OUT.mkdir(parents=True, exist_ok=True)
            np.savetxt(OUT.parent / f"validate_{case.name}_{cut}.csv",
                       np.column_stack([ref["depth_lo_mm"], ref["depth_hi_mm"], dose, sd]),
                       delimiter=",", header="depth_lo_mm,depth_hi_mm,dose_gy,dose_std_gy")


if __name__ == "__main__":
    main()
