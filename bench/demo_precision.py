"""Issue 30's demo target, and what the tumour's per-tet σ costs: resolution or time.

The target: ``make demo`` (defaults) with a median per-tet σ ≤ 2 % in the tumour's accumulated
dose and ≤ 5 % per phase, the demo ≤ 3 min warm. A tet's σ falls as 1/√(mass × histories), so
the same σ comes from larger tumour tets or from more histories. Each variant is one demo
(``tetdose demo --size-mm tumour=H --histories N``, run through :func:`tetdose.study.run_study`
in this process). Prints per variant:

- the tumour's tets, their median volume [mm³] and mass [mg] (the CT voxels: 64 mm³);
- the meshed tumour's volume against its label's voxel volume (how faithful the mesh is);
- the density mapping's RMDE and mass error in the tumour's voxels (what the coarser mesh costs);
- the median per-tet σ of the accumulated dose and of the phases (median over phases);
- the dose stage's and the whole demo's wall time [s];
- by σ ∝ 1/√N, the histories per phase that 5 % per phase needs, and the dose stage's and
  the demo's wall time at that many (the other stages unchanged).

Run: ``NUMBA_CACHE_DIR=.numba-cache .venv/bin/python bench/demo_precision.py OUT [VARIANT …]``,
a variant ``H:N`` (tumour target edge [mm], ``d`` for the default; histories per phase), default
``d:40000 14:40000``. Run the demo once first, so that nothing is compiled in the timings.
"""

from __future__ import annotations

import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from tetdose.core.io import read_image, read_mesh
from tetdose.study import StudyConfig, run_study

TARGET_PHASE_PCT, TARGET_ACC_PCT, TARGET_S = 5.0, 2.0, 180.0


def variant(out: Path, size: str, histories: int) -> None:
    """Run one demo and print its row."""
    sizes = () if size == "d" else (("tumour", float(size)),)
    config = replace(StudyConfig(), histories=histories, mesh_size_mm=sizes)
    start = time.perf_counter()
    s = run_study(config, out, log=lambda line: None)
    total = time.perf_counter() - start
    label = s["phantom"]["labels"]["tumour"]
    mesh = read_mesh(out / "phantom" / "organ_mesh.vtu")
    vol = mesh.volumes_mm3[mesh.region == label]
    labels = np.asarray(read_image(out / "phantom" / "labels.nrrd").array)
    voxel_mm3 = float(np.prod(s["phantom"]["spacing_mm"]))
    label_mm3 = float(np.count_nonzero(labels == label)) * voxel_mm3
    p = s["precision"]["tumour"]
    sig = p["median_sigma_pct"]
    m = s["mapping"]["l2 exact (tetdose)"]["tumour"]
    dose_s = s["seconds"]["dose"]
    need = histories * (sig["phase_median"] / TARGET_PHASE_PCT) ** 2
    dose_need = dose_s * need / histories
    print(f"tumour edge {size:>3} mm, {histories:6d} histories: {p['tets']:5d} tets, median "
          f"{np.median(vol):5.1f} mm³ / {p['median_tet_mass_mg']:5.1f} mg; volume "
          f"{100 * (vol.sum() / label_mm3 - 1):+5.1f} % of the label's; mapping RMDE "
          f"{m['rmde_pct']:5.2f} %, mass error {m['mass_error_pct']:5.2f} %")
    print(f"    σ accumulated {sig['accumulated']:5.2f} % (target ≤ {TARGET_ACC_PCT:g}), per "
          f"phase {sig['phase_median']:5.2f} % (≤ {TARGET_PHASE_PCT:g}); dose {dose_s:5.1f} s, "
          f"demo {total:5.1f} s (≤ {TARGET_S:g}); 5 % per phase needs {need:8.0f} histories: "
          f"dose {dose_need:5.0f} s, demo {total - dose_s + dose_need:5.0f} s", flush=True)


def main() -> None:
    out = Path(sys.argv[1])
    for spec in sys.argv[2:] or ["d:40000", "14:40000"]:
        size, n = spec.split(":")
        variant(out / f"tumour_{size}_{n}", size, int(float(n)))


if __name__ == "__main__":
    main()
