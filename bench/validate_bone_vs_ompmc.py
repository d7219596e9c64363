"""Dose inside ICRP cortical bone (1.85 g/cm³), tetdose against ompmc's ICRPBONE521ICRU (issue 32).

Run: ``NUMBA_CACHE_DIR=.numba-cache .venv/bin/python bench/validate_bone_vs_ompmc.py [N_TETDOSE]
[N_OMPMC] [--material NAME] [--beams 6MV,e10MeV]`` (defaults 1e6 and 4e4; needs
``tetdose[ompmc]``; about 10 min on 2 cores).

Phantoms (``tests/verification/test_bone_vs_ompmc.py``, its slow test): 15 × 15 lateral voxels
of 10 mm, 1 mm deep, the layout of ``tests/verification/test_vs_ompmc.py``; water with a slab of
bone named ``--material``
(default ``icrp_cortical_bone``, the composition of ICRP Publication 23 as in NIST's "Bone,
Cortical (ICRP)" and EGSnrc's ICRPBONE), given the density 1.85 g/cm³:

- ``6MV``: the Mohan 6 MV spectrum, 50 × 50 mm² parallel field, bone at 30–50 mm depth, the mean
  dose over 32–48 mm (the column of 3 × 3 central voxels);
- ``e10MeV``: 10 MeV electrons, 50 × 50 mm², bone at 10–20 mm, the mean dose over 11–19 mm.

Both codes: 10 keV electron and photon cut-offs, the same source particles (tetdose's sampler,
replayed by ompmc), ompmc's media chosen by :mod:`tetdose.coupling.ompmc` (bone →
ICRPBONE521ICRU, recorded). Prints tetdose / ompmc − 1 inside the bone with σ (both runs' batch
σ), and in the water before the bone as a control. Issue 32's criteria: 1 % (6 MV) and 1.5 %
(10 MeV electrons) inside the bone.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "verification"))
from test_bone_vs_ompmc import CASES, run_case  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("n_tetdose", nargs="?", type=float, default=1e6)
    ap.add_argument("n_ompmc", nargs="?", type=float, default=4e4)
    ap.add_argument("--material", default="icrp_cortical_bone")
    ap.add_argument("--beams", default="6MV,e10MeV")
    args = ap.parse_args()
    for name in args.beams.split(","):
        case = CASES[name]
        r = run_case(case, args.material, int(args.n_tetdose), int(args.n_ompmc))
        ok = abs(r["bone"]) <= case.tolerance
        print(f"{name:7s} {args.material} (ompmc {r['pegs']}): bone {case.score_mm[0]}–"
              f"{case.score_mm[1]} mm tetdose/ompmc − 1 = {100 * r['bone']:+.2f} ± "
              f"{100 * r['bone_sigma']:.2f} % (σ tetdose {100 * r['bone_sigma_tetdose']:.2f} %, "
              f"ompmc {100 * r['bone_sigma_ompmc']:.2f} %; criterion ±{100 * case.tolerance:.1f} %: "
              f"{'met' if ok else 'NOT met'}); water {case.control_mm[0]}–{case.control_mm[1]} mm "
              f"{100 * r['water']:+.2f} ± {100 * r['water_sigma']:.2f} %", flush=True)


if __name__ == "__main__":
    main()
