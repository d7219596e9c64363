"""Build-up dose / kerma under the surface and the lung dose behind water, tetdose against ompmc
(EGSnrc physics).

Run: ``NUMBA_CACHE_DIR=.numba-cache .venv/bin/python bench/buildup_vs_ompmc.py [N_TETDOSE]
[N_OMPMC] [--lung N_TETDOSE N_OMPMC] [--estepe 0.25,0.05]`` (defaults 2e6 and 1e5; needs
``tetdose[ompmc]``, about 10 min on 2 cores, plus about 4 min for ``--lung 6e6 4e5``).

The phantom, beams and central-axis column of ``tests/verification/test_vs_ompmc.py`` (water,
2 MeV and the Mohan 6 MV spectrum, 100 × 100 mm² parallel fields, 10 keV electron and photon
cut-offs, 521icru): for the layers 0–1 … 5–6 mm, each code's dose divided by tetdose's collision
kerma (track length, kerma mode, same column) with σ from 10 batches, and the dose relative to
ompmc's D_max (the issue-19 criterion: within 3 % of it). With ``--lung``: the water / lung
(0.26 g/cm³) / water slab of the same test, 30 × 30 mm², the mean dose in the lung 5 mm from
its interfaces, tetdose / ompmc − 1 with σ, for each ESTEPE of ``--estepe`` against one ompmc
run (the issue-19 criterion: within 1 %). README "Where kerma ≠ dose".
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "verification"))
import test_vs_ompmc as ref  # noqa: E402

from tetdose.coupling.ompmc import OmpmcOptions, simulate_ompmc  # noqa: E402
from tetdose.transport import TransportSettings, simulate  # noqa: E402

CUTOFF_MEV = 0.01
LAYERS_MM = range(6)


def buildup(n_tetdose: int, n_ompmc: int) -> None:
    """Dose / kerma in the first six 1 mm layers of water, 2 MeV and 6 MV (module docstring)."""
    for beam in ("2MeV", "6MV"):
        rho, lab = ref._phantom(False)
        plan = ref._plan(beam, 100.0)
        runs = {
            "tetdose": simulate(rho, plan, TransportSettings(
                n_tetdose, 10, 11, energy_cutoff_mev=CUTOFF_MEV, electron_cutoff_mev=CUTOFF_MEV),
                labels=lab, progress=False),
            "ompmc": simulate_ompmc(rho, plan, TransportSettings(
                n_ompmc, 10, 12, energy_cutoff_mev=CUTOFF_MEV), labels=lab, progress=False,
                options=OmpmcOptions(electron_cutoff_mev=CUTOFF_MEV)),
            "kerma": simulate(rho, plan, TransportSettings(
                n_tetdose, 10, 13, energy_cutoff_mev=CUTOFF_MEV, physics="kerma"),
                labels=lab, progress=False)}
        cols = {k: ref._column(r, rho.grid, 100.0) for k, r in runs.items()}
        mass = cols["kerma"][1]
        kerma = [ref._bin(cols["kerma"][0], mass, z, z + 1)[0] for z in LAYERS_MM]
        d_max = max(ref._bin(cols["ompmc"][0], mass, z, z + 2)[0] for z in range(6, 30, 2))
        for name in ("tetdose", "ompmc"):
            layers = [ref._bin(cols[name][0], mass, z, z + 1) for z in LAYERS_MM]
            print(f"{beam} {name:8s} D/K " + " / ".join(f"{d / k:.3f}" for (d, _), k in zip(
                layers, kerma, strict=True)) + "  σ " + " / ".join(
                f"{s / k:.3f}" for (_, s), k in zip(layers, kerma, strict=True))
                + "  D/D_max(ompmc) " + " / ".join(f"{d / d_max:.3f}" for d, _ in layers),
                flush=True)


def lung(n_tetdose: int, n_ompmc: int, estepe: list[float]) -> None:
    """Mean lung dose of the water / lung / water slab, tetdose / ompmc − 1 (module docstring)."""
    lo, hi = ref.LUNG_MM[0] + 5, ref.LUNG_MM[1] - 5
    for beam in ("2MeV", "6MV"):
        rho, lab = ref._phantom(True)
        plan = ref._plan(beam, 30.0)
        o = simulate_ompmc(rho, plan, TransportSettings(n_ompmc, 10, 22,
                                                        energy_cutoff_mev=CUTOFF_MEV),
                           labels=lab, progress=False,
                           options=OmpmcOptions(electron_cutoff_mev=CUTOFF_MEV))
        eo, mass = ref._column(o, rho.grid, 30.0)
        do, so = ref._bin(eo, mass, lo, hi)
        for f in estepe:
            t = simulate(rho, plan, TransportSettings(
                n_tetdose, 10, 21, energy_cutoff_mev=CUTOFF_MEV, electron_cutoff_mev=CUTOFF_MEV,
                max_energy_loss_fraction=f), labels=lab, progress=False)
            dt, st = ref._bin(ref._column(t, rho.grid, 30.0)[0], mass, lo, hi)
            print(f"{beam} lung {lo}-{hi} mm, ESTEPE {f}: tetdose / ompmc − 1 = "
                  f"{100 * (dt / do - 1):+.2f} ± {100 * dt / do * np.hypot(st / dt, so / do):.2f} %",
                  flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("n_tetdose", nargs="?", type=float, default=2e6)
    ap.add_argument("n_ompmc", nargs="?", type=float, default=1e5)
    ap.add_argument("--lung", nargs=2, type=float, metavar=("N_TETDOSE", "N_OMPMC"))
    ap.add_argument("--estepe", default="0.25")
    args = ap.parse_args()
    buildup(int(args.n_tetdose), int(args.n_ompmc))
    if args.lung:
        lung(int(args.lung[0]), int(args.lung[1]), [float(f) for f in args.estepe.split(",")])


if __name__ == "__main__":
    main()
