"""Sliver repair on real masks: the MMG output, relocation only, relocation + flips (the default).

    python bench/bench_slivers.py [--cases lung lung8 abdomen3 abdomen9]

Each case is meshed once by ``tetdose.meshing.conforming_mesh``; the MMG output handed to the
sliver pass is kept and passed through (1) nothing, (2) vertex relocation alone
(``quality.relocated``, junction and ridge vertices fixed: the pass before flips.py) and (3) the
whole pass (``quality.removed_slivers``). Per row: tets, pass time [s], smallest and median
dihedral angle [°], tets below 10°, worst |volume error| per label [%], mean surface distance
[mm] (``mesh_checks``), boundary and interface faces, coincident vertices.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
LUNG = SHARED / "lung-elastix" / "3DCT_lung_baseline_mask.mha"
ABDOMEN = SHARED / "abdomen-dicom" / "example_seg_dicom.nii.gz"
CASES = {"lung": (LUNG, [1], None), "lung8": (LUNG, [1], 8.0),
         "abdomen3": (ABDOMEN, [1, 5, 6], None),
         "abdomen9": (ABDOMEN, [1, 5, 6, 7, 8, 20, 32, 33, 52], None)}


def _row(case: str, what: str, mesh, image, ids: list[int], dt: float) -> None:  # noqa: ANN001
    from tetdose.meshing import mesh_checks
    from tetdose.meshing.checks import dihedral_angles_deg

    angles = dihedral_angles_deg(mesh.points_mm, mesh.tets).min(axis=1)
    r = mesh_checks(mesh, image, ids)
    errs = [abs(e["volume_error_pct"]) for e in r["labels"].values()]
    dist = [e["surface_distance_mean_mm"] for e in r["labels"].values()]
    c = r["conformity"]
    print(f"{case:<10}{what:<12}{mesh.n_tets:>8}{dt:>7.2f}{angles.min():>7.2f}"
          f"{r['median_dihedral_deg']:>7.1f}{int((angles < 10).sum()):>6}{max(errs):>9.3f}"
          f"{np.mean(dist):>8.3f}{c['boundary_faces']:>8}{c['interface_faces']:>7}"
          f"{c['coincident_vertices']:>5}", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", nargs="*", choices=tuple(CASES), default=list(CASES))
    args = parser.parse_args()
    if not SHARED.is_dir():
        print(f"{SHARED} not found: nothing to measure")
        return
    import tetdose.meshing.mmg as mmg
    from tetdose.core.io import read_image
    from tetdose.core.mesh import TetMesh
    from tetdose.meshing.flips import tet_quality
    from tetdose.meshing.quality import relocated, removed_slivers

    seen: dict[str, tuple] = {}

    def keep(points, tets, region, threshold):  # noqa: ANN001, ANN202
        seen["input"] = (points, tets, region, threshold)
        return points, tets, region  # the bench runs the passes itself below

    mmg.removed_slivers = keep
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    print(f"{'case':<10}{'pass':<12}{'tets':>8}{'s':>7}{'min°':>7}{'med°':>7}{'<10°':>6}"
          f"{'max|dV|%':>9}{'dist mm':>8}{'bfaces':>8}{'iface':>7}{'dup':>5}")
    for case in args.cases:
        path, ids, size = CASES[case]
        image = read_image(path)
        t0 = time.perf_counter()
        mmg.conforming_mesh(image, ids, size)
        print(f"{case:<10}meshing (MMG) {time.perf_counter() - t0:.1f} s", flush=True)
        points, tets, region, threshold = seen["input"]
        _row(case, "MMG output", TetMesh(points, tets, region), image, ids, 0.0)
        t0 = time.perf_counter()
        bad = np.flatnonzero(tet_quality(points, tets) < threshold)
        moved, _ = relocated(points, tets, region, threshold, bad)
        dt = time.perf_counter() - t0
        _row(case, "relocation", TetMesh(moved, tets, region), image, ids, dt)
        t0 = time.perf_counter()
        out = removed_slivers(points, tets, region, threshold)
        _row(case, "+ flips", TetMesh(*out), image, ids, time.perf_counter() - t0)


if __name__ == "__main__":
    main()
