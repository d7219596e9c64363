"""Build-up dose / kerma under the surface, tetdose against ompmc (EGSnrc physics), 1 mm layers.

Run: ``NUMBA_CACHE_DIR=.numba-cache .venv/bin/python bench/buildup_vs_ompmc.py [N_TETDOSE]
[N_OMPMC]`` (defaults 2e6 and 1e5; needs ``tetdose[ompmc]``, about 10 min on 2 cores).

The phantom, beams and central-axis column of ``tests/verification/test_vs_ompmc.py`` (water,
2 MeV and the Mohan 6 MV spectrum, 100 × 100 mm² parallel fields, 10 keV electron and photon
cut-offs, 521icru): for the layers 0–1 … 5–6 mm, each code's dose divided by tetdose's collision
kerma (track length, kerma mode, same column) with σ from 10 batches, and the dose relative to
ompmc's D_max (the issue-19 criterion: within 3 % of it). README "Where kerma ≠ dose".
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "verification"))
import test_vs_ompmc as ref  # noqa: E402

from tetdose.coupling.ompmc import OmpmcOptions, simulate_ompmc  # noqa: E402
from tetdose.transport import TransportSettings, simulate  # noqa: E402

CUTOFF_MEV = 0.01
LAYERS_MM = range(6)


def main() -> None:
    n_tetdose = int(float(sys.argv[1])) if len(sys.argv) > 1 else 2_000_000
    n_ompmc = int(float(sys.argv[2])) if len(sys.argv) > 2 else 100_000
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


if __name__ == "__main__":
    main()
