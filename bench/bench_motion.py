"""Benchmark of the breathing-motion pipeline: density update, voxelize, 4D-CT write.

Issue 3's figure: a 10-phase 4D-CT of a ~100 000-tetrahedron organ on a 512×512×120 grid, time
per stage (motion, density update, voxelize, DICOM write) and the cost per phase against one
``voxelize``. Defaults are that size; ``--small`` runs a quick version.

    NUMBA_CACHE_DIR=/tmp/numba-bench .venv/bin/python bench/bench_motion.py [--small]
"""

from __future__ import annotations

import argparse
import itertools
import tempfile
import time
from pathlib import Path

import numpy as np

from tetdose.core.image import Image, ImageGrid
from tetdose.core.mesh import TetMesh
from tetdose.core.voxelize import voxelize
from tetdose.motion import BreathingModel, update_series
from tetdose.motion.ct4d import virtual_4dct, write_4dct


def kuhn_box(n: int, size_mm: float, centre_mm: np.ndarray) -> TetMesh:
    """n³ cubes × 6 tetrahedra, centred on ``centre_mm``, with a smooth density [g/cm³]."""
    ax = np.linspace(-size_mm / 2, size_mm / 2, n + 1)
    z, y, x = np.meshgrid(ax, ax, ax, indexing="ij")
    pts = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1) + centre_mm
    base = np.array(list(itertools.product(range(n), repeat=3)))[:, ::-1]  # (i, j, k)
    tets = []
    for perm in itertools.permutations(range(3)):
        c = base.copy()
        ids = [c]
        for a in perm:
            c = c.copy()
            c[:, a] += 1
            ids.append(c)
        tets.append(np.stack([(v[:, 2] * (n + 1) + v[:, 1]) * (n + 1) + v[:, 0] for v in ids], 1))
    mesh = TetMesh(pts, np.concatenate(tets)).with_fixed_orientation()
    r = np.linalg.norm(pts - centre_mm, axis=1) / size_mm
    return mesh.with_data(point_data={"density": 1.05 - 0.6 * r**2})


def timed(label: str, fn, *args, **kwargs):  # noqa: ANN001, ANN201
    t0 = time.perf_counter()
    out = fn(*args, **kwargs)
    dt = time.perf_counter() - t0
    print(f"{label:<40s} {dt:9.3f} s")
    return out, dt


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--small", action="store_true", help="26³→10³ cells, 128×128×40 grid")
    p.add_argument("--phases", type=int, default=10)
    p.add_argument("--no-dicom", action="store_true", help="skip the DICOM write stage")
    p.add_argument("--fem", action="store_true", help="also time one surface-driven FEM phase")
    args = p.parse_args()
    n, size = ((10, (128, 128, 40)) if args.small else (26, (512, 512, 120)))
    grid = ImageGrid([-250.0, -250.0, -150.0], [500 / size[0], 500 / size[1], 300 / size[2]],
                     np.eye(3), size)
    ct = Image(np.full(grid.shape, -700, dtype=np.int16), grid)
    mesh = kuhn_box(n, 160.0, np.zeros(3))
    print(f"mesh: {mesh.n_tets} tetrahedra, {mesh.n_points} vertices; grid {grid.size}; "
          f"{args.phases} phases")

    tiny = kuhn_box(2, 20.0, np.zeros(3))
    _, compile_s = timed("warm-up (numba compile / cache load)", voxelize, tiny,
                         tiny.point_data["density"], grid)
    series, t_motion = timed("breathing motion (all phases)", BreathingModel(15.0).series,
                             mesh, args.phases)
    if args.fem:
        from tetdose.motion.fem import boundary_surface, surface_driven_points

        target = boundary_surface(mesh.moved(series.points_mm[0]))[0]
        timed("surface-driven FEM, 1 phase, 4 increments", surface_driven_points, mesh, target)
    (series_l2, reports), t_l2 = timed("density update l2 (all phases)", update_series, series)
    _, t_lsq = timed("density update lsq (all phases)", update_series, series, method="lsq")
    _, t_vox1 = timed("one voxelize (reference phase)", voxelize, mesh,
                      mesh.point_data["density"], grid)
    images, t_4d = timed("virtual 4D-CT (voxelize + HU, all)", virtual_4dct, series_l2, ct)
    t_dcm = 0.0
    with tempfile.TemporaryDirectory() as tmp:
        _, t_nrrd = timed("write NRRD (all phases)", write_4dct, images, Path(tmp) / "n",
                          phase_percent=series.phase_percent, fmt="nrrd")
        if not args.no_dicom:
            _, t_dcm = timed("write DICOM (all phases)", write_4dct, images, Path(tmp) / "d",
                             phase_percent=series.phase_percent, fmt="dicom")
    k = args.phases
    drift = max(abs(r.mass_change_rel) for r in reports)
    print(f"\nper phase: motion {t_motion / k:.3f} s, l2 update {t_l2 / k:.3f} s, lsq update "
          f"{t_lsq / k:.3f} s, 4D-CT {t_4d / k:.3f} s, DICOM {t_dcm / k:.3f} s")
    print(f"4D-CT per phase / one voxelize = {t_4d / k / t_vox1:.2f}; worst relative mass "
          f"drift (l2) {drift:.1e}; compile/cache {compile_s:.2f} s")
    total = t_motion + t_l2 + t_4d + t_dcm
    print(f"total (motion + l2 + 4D-CT + DICOM) {total:.1f} s")


if __name__ == "__main__":
    main()
