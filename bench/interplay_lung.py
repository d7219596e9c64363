"""Interplay of the README's VMAT plan with breathing on the real lung CT (README "Interplay").

Run: ``NUMBA_CACHE_DIR=.numba-cache .venv/bin/python bench/interplay_lung.py OUT [FRACTIONS]
[HISTORIES]`` (defaults 8 and 2e4 per phase; about 10 min for the meshing, mapping and phases
and 9 min for the course on a loaded 2-core VM).

Inputs (``../shared/data/lung-elastix``): the lung mask, plus a synthetic 30 mm tumour (label 2,
0 HU in the CT copy written to OUT) centred on the plan's isocentre (−70, −34, −1264) mm in the
right lung — the CT has no tumour. Then ``tetdose mesh`` (lung 25 mm, tumour 5 mm edges),
``map``, ``deform --breathing`` (10 phases, 10 mm, 4 s; reference end-exhale = 50 %) and
``dose4d`` with a regular 4 s cycle, random start phases, the course of FRACTIONS fractions,
kerma (track length) for speed, the mesh alone (no ``--like``: the chest wall is not in it).
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np

from tetdose.core.io import read_image, write_image

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "lung-elastix"
ISO_MM = np.array([-70.0, -34.0, -1264.0])
RADIUS_MM = 15.0
PLAN_PAGE = Path(__file__).resolve().parents[1] / "docs" / "user-guide" / "plans.md"


def plan_toml() -> str:
    """The user guide's vmat.toml (docs/user-guide/plans.md) with [regions] tumour = 2."""
    text = PLAN_PAGE.read_text()
    start = text.index("# vmat.toml\n") + len("# vmat.toml\n")
    return text[start:text.index("```", start)] + "\n[regions]\ntumour = 2\n"


def inputs(out: Path) -> None:
    mask = read_image(DATA / "3DCT_lung_baseline_mask.mha")
    ct = read_image(DATA / "3DCT_lung_baseline_small.mha")
    lab = (np.asarray(mask.array).reshape(-1) > 0).astype(np.int16)
    lab[(np.linalg.norm(mask.grid.voxel_centers_mm() - ISO_MM, axis=1) < RADIUS_MM)
        & (lab > 0)] = 2
    write_image(out / "labels.mha", mask.with_array(lab.reshape(mask.array.shape)))
    hu = np.asarray(ct.array).reshape(-1).astype(np.int16).copy()
    hu[np.linalg.norm(ct.grid.voxel_centers_mm() - ISO_MM, axis=1) < RADIUS_MM] = 0
    write_image(out / "ct_tumour.mha", ct.with_array(hu.reshape(ct.array.shape)))
    (out / "vmat.toml").write_text(plan_toml())


def main() -> None:
    out = Path(sys.argv[1])
    fractions = sys.argv[2] if len(sys.argv) > 2 else "8"
    histories = sys.argv[3] if len(sys.argv) > 3 else "2e4"
    out.mkdir(parents=True, exist_ok=True)
    inputs(out)
    td = [sys.executable, "-m", "tetdose"]
    for args in (["mesh", "--labels", "labels.mha", "--size-mm", "1=25,2=5", "-o", "mesh.vtu"],
                 ["map", "--ct", "ct_tumour.mha", "--mesh", "mesh.vtu", "-o", "mapped.vtu"],
                 ["deform", "--mesh", "mapped.vtu", "--breathing", "--n-phases", "10",
                  "--amplitude-mm", "10", "--period-s", "4", "-o", "phases"],
                 ["dose4d", "--phases", "phases", "--plan", "vmat.toml", "--physics", "kerma",
                  "--histories", histories, "--breathing-period-s", "4", "--start-phase",
                  "random", "--fractions", fractions, "--target", "tumour", "--static-phase",
                  "50", "--seed", "1", "-o", "course"]):
        subprocess.run([*td, *args, "-q"], cwd=out, check=True)


if __name__ == "__main__":
    main()
