"""Dose mode vs kerma mode: CPU time per 2 MeV photon history in water, one thread.

Run: ``NUMBA_CACHE_DIR=... .venv/bin/python bench/bench_dose.py [HISTORIES]`` (default 20 000).
A 300 mm water box of 30³ voxels (10 mm) and the same box as 30³ × 6 tets; a 2 MeV
100 × 100 mm² parallel field along z from the surface. Kerma mode (track-length estimator) against
dose mode (electrons transported, analog deposition) at electron cut-offs of 0.2 and 0.01 MeV
(photon cut-off 0.01 MeV, ESTEPE 0.25). The first call of each configuration is a warm-up
(compile/load, reported); the figures are the best of three runs in CPU time
(``time.process_time``), with electron steps and tracks per history from the run record.
"""

from __future__ import annotations

import sys
import time

import numba
import numpy as np

from tetdose.core.image import Image, ImageGrid
from tetdose.core.mesh import TetMesh
from tetdose.transport import PhotonSource, Plan, TransportSettings, simulate

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from bench_transport import box  # noqa: E402

PLAN = Plan((PhotonSource("parallel", [0, 0, -150.0], [0, 0, 1], energies_mev=[2.0],
                          field_mm=[100.0, 100.0]),), materials={1: "water"})


def water_box(n: int = 30, size_mm: float = 300.0):  # noqa: ANN201
    mesh, _ = box(n, size_mm)
    mesh = TetMesh(mesh.points_mm, mesh.tets, np.ones(mesh.n_tets, int),
                   {"density": np.ones(mesh.n_points)})
    spacing = np.full(3, size_mm / n)
    grid = ImageGrid(spacing / 2 - size_mm / 2, spacing, np.eye(3), (n, n, n))
    labels = Image(np.ones(grid.shape, np.int32), grid)
    return mesh, Image(np.ones(grid.shape), grid), labels


def timed(geom, labels, settings: TransportSettings) -> tuple[float, float, dict]:  # noqa: ANN001
    t0 = time.perf_counter()
    simulate(geom, PLAN, TransportSettings(200, 2, physics=settings.physics,
                                           electron_cutoff_mev=settings.electron_cutoff_mev),
             labels=labels, progress=False)
    warm = time.perf_counter() - t0
    best, rec = np.inf, {}
    for _ in range(3):
        t0 = time.process_time()
        r = simulate(geom, PLAN, settings, labels=labels, progress=False)
        best = min(best, time.process_time() - t0)
        rec = r.record()
    return best / settings.n_histories * 1e6, warm, rec


def main() -> None:
    n = int(float(sys.argv[1])) if len(sys.argv) > 1 else 20_000
    numba.set_num_threads(1)
    mesh, density, labels = water_box()
    print(f"2 MeV 100 x 100 mm2 parallel beam, 300 mm water box, {n} histories, 1 thread")
    print(f"{'world':6s} {'physics':24s} {'µs/history':>11s} {'× kerma':>8s} {'steps/hist':>10s} "
          f"{'tracks/hist':>11s} {'warm-up s':>9s}")
    for name, geom, lab in (("voxel", density, labels), ("mesh", mesh, None)):
        base = None
        for physics, cut in (("kerma", 0.2), ("dose", 0.2), ("dose", 0.01)):
            st = TransportSettings(n, 10, 1, physics=physics, electron_cutoff_mev=cut)
            us, warm, rec = timed(geom, lab, st)
            base = base or us
            label = "kerma" if physics == "kerma" else f"dose, e cut-off {cut:g} MeV"
            print(f"{name:6s} {label:24s} {us:11.1f} {us / base:8.1f} "
                  f"{rec.get('electron_steps', 0) / n:10.1f} "
                  f"{rec.get('electron_tracks', 0) / n:11.2f} {warm:9.1f}", flush=True)


if __name__ == "__main__":
    main()
