"""Dose with electrons on the real thorax CT against ompmc (EGSnrc physics), the guide's VMAT plan.

Run: ``NUMBA_CACHE_DIR=.numba-cache .venv/bin/python bench/validate_real_ct_vs_ompmc.py
[--histories 3e6] [--ompmc-histories 3e5]`` (needs ``tetdose[ompmc]`` and ``../shared``).

The plan is the ``vmat.toml`` block of docs/user-guide/plans.md ("A VMAT plan on the real CT":
two 6 MV arcs around the right lung) on ``../shared/data/lung-elastix/3DCT_lung_baseline_small.mha``
(Schneider calibration). tetdose (dose mode) and ompmc (PEGS 700icru, so both follow electrons to
0.189 MeV and photons to 0.01 MeV) transport the same source particles; tetdose in kerma mode
finds the field: the voxels above 50 % of the maximum kerma. Printed per density band of those
voxels: mass [g], the mass-weighted mean dose per source photon [Gy] of each engine with its σ
(batches), the ratio tetdose / ompmc with σ, and dose / kerma. Single low-mass lung voxels are
noisy (per-voxel σ 15–22 % at 3·10⁵ histories), so only mass-weighted means are compared.
Voxels below 0.0435 g/cm³ (airways) are shown apart: ompmc scores no energy there
(:data:`tetdose.coupling.ompmc.UNSCORED_BELOW_G_CM3`), so the "all" row starts above it.
"""

from __future__ import annotations

import argparse
import re
import time
import tomllib
from pathlib import Path

import numpy as np

from tetdose.core.calibration import HUCalibration
from tetdose.core.io import read_ct
from tetdose.coupling.ompmc import UNSCORED_BELOW_G_CM3, OmpmcOptions, simulate_ompmc
from tetdose.plan import Plan
from tetdose.transport import TransportSettings, World, simulate

ROOT = Path(__file__).resolve().parents[1]
CT = ROOT.parent / "shared" / "data" / "lung-elastix" / "3DCT_lung_baseline_small.mha"
#: Density bands [g/cm³] of the in-field voxels.
BANDS = ((0.0, UNSCORED_BELOW_G_CM3), (UNSCORED_BELOW_G_CM3, 3.0), (UNSCORED_BELOW_G_CM3, 0.2),
         (0.2, 0.5), (0.5, 1.2), (1.2, 3.0))
#: Electron cut-off [MeV] kinetic of PEGS 700icru (AE 0.700 MeV total); photons 0.01 MeV.
CUTOFF_MEV = 0.189
BATCHES = 10
PLAN_PAGE = "docs/user-guide/plans.md"  # the VMAT plan of "A VMAT plan on the real CT"


def readme_plan() -> Plan:
    """The user guide's ``# vmat.toml`` block (docs/user-guide/plans.md) as a :class:`Plan`."""
    text = (ROOT / PLAN_PAGE).read_text()
    block = re.search(r"```toml\n# vmat.toml\n(.*?)```", text, re.S)
    if block is None:
        raise SystemExit(f"{PLAN_PAGE} has no '# vmat.toml' block")
    return Plan.from_dict(tomllib.loads(block.group(1)))


def per_batch_dose(result) -> np.ndarray:  # noqa: ANN001
    """(batches, voxels) dose per source particle [MeV/g] of each batch."""
    return (result.energy_per_batch_mev / result.histories_per_batch[:, None]
            / result.mass_g.reshape(1, -1))


def band_mean(dose_b: np.ndarray, mass: np.ndarray, sel: np.ndarray) -> tuple[float, float]:
    """Mass-weighted mean of the selected voxels and its σ over batches."""
    means = dose_b[:, sel] @ mass[sel] / mass[sel].sum()
    return float(means.mean()), float(means.std(ddof=1) / np.sqrt(len(means)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--histories", type=float, default=3e6)
    ap.add_argument("--ompmc-histories", type=float, default=3e5)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    if not CT.exists():
        raise SystemExit(f"{CT} not found: this bench needs ../shared beside the checkout")
    ct = read_ct(CT)
    density = ct.with_array(HUCalibration.schneider2000().density(ct.array).astype(np.float64))
    plan = readme_plan().resolved(World(density=density))
    runs = {}
    for name, physics, n in (("kerma", "kerma", args.histories), ("tetdose", "dose", args.histories)):
        t0 = time.perf_counter()
        runs[name] = simulate(density, plan, TransportSettings(
            int(n), BATCHES, args.seed, physics=physics, electron_cutoff_mev=CUTOFF_MEV,
            energy_cutoff_mev=0.01), progress=False)
        print(f"{name}: {int(n):.2e} histories, {time.perf_counter() - t0:.1f} s", flush=True)
    t0 = time.perf_counter()
    runs["ompmc"] = simulate_ompmc(
        density, plan, TransportSettings(int(args.ompmc_histories), BATCHES, args.seed,
                                         electron_cutoff_mev=CUTOFF_MEV, energy_cutoff_mev=0.01),
        options=OmpmcOptions(pegs="700icru", electron_cutoff_mev=CUTOFF_MEV), progress=False)
    print(f"ompmc: {int(args.ompmc_histories):.2e} histories, {time.perf_counter() - t0:.1f} s "
          f"(media {runs['ompmc'].extra['media']})", flush=True)
    mass = runs["tetdose"].mass_g.reshape(-1)
    rho = density.array.reshape(-1)  # the results' voxel order is the image's (z, y, x) ravel
    voxel_cm3 = float(np.prod(density.grid.spacing_mm)) / 1e3
    if not np.allclose(mass, rho * voxel_cm3, rtol=1e-6, atol=1e-12):
        raise SystemExit("voxel order of the result differs from the image's")
    dose = {k: per_batch_dose(r) for k, r in runs.items()}
    kerma = dose["kerma"].mean(axis=0)
    field = kerma > 0.5 * kerma.max()
    mev_g_to_gy = 1.602176634e-13 * 1e3
    print(f"\nin-field voxels (kerma > 50 % of its maximum): {field.sum()}, "
          f"{mass[field].sum():.1f} g, median density {np.median(rho[field]):.3f} g/cm³")
    print(f"{'band g/cm³':>13s} {'voxels':>6s} {'mass g':>7s} {'tetdose Gy':>11s} {'ompmc Gy':>11s} "
          f"{'t/o':>6s} {'σ':>6s} {'D/K':>5s}")
    for lo, hi in BANDS:
        sel = field & (rho >= lo) & (rho < hi)
        if sel.sum() == 0 or mass[sel].sum() == 0.0:
            continue
        (t, st), (o, so), (k, _) = (band_mean(dose[n], mass, sel)
                                    for n in ("tetdose", "ompmc", "kerma"))
        ratio = t / o if o > 0.0 else np.inf
        sr = ratio * np.hypot(st / t, so / o) if o > 0.0 else np.nan
        print(f"{lo:6.4f}–{hi:6.4f} {sel.sum():6d} {mass[sel].sum():7.1f} {t * mev_g_to_gy:11.4e} "
              f"{o * mev_g_to_gy:11.4e} {ratio:6.3f} {sr:6.3f} {t / k:5.2f}")
    for name in ("tetdose", "ompmc"):
        e = runs[name].energy_per_batch_mev.sum(axis=1) / runs[name].histories_per_batch
        print(f"{name}: energy deposited {e.mean():.4f} ± {e.std(ddof=1) / np.sqrt(BATCHES):.4f} "
              f"MeV per photon")


if __name__ == "__main__":
    main()
