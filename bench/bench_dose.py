"""Dose mode vs kerma mode: CPU time per 2 MeV photon history in water, one thread.

Run: ``NUMBA_CACHE_DIR=... .venv/bin/python bench/bench_dose.py [HISTORIES]`` (default 20 000);
``bench/bench_dose.py buildup [HISTORIES]`` (default 2·10⁶) prints instead dose/kerma per 1 mm
layer of water under a 2 MeV 100 × 100 mm² field (central 24 × 24 mm²) and in lung (0.26 g/cm³)
behind 30 mm of water under a 30 × 30 mm² field (0.01 MeV electron cut-off, two threads).
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


def _layers(rho: np.ndarray, lab: np.ndarray, grid: ImageGrid, field_mm: float, n: int,
            physics: str, centre: slice) -> np.ndarray:
    """(10 batches, depth) energy per mass in the central columns [MeV/g per history]."""
    plan = Plan((PhotonSource("parallel", (0.0, 0.0, -5.0), (0, 0, 1), energies_mev=(2.0,),
                              field_mm=(field_mm, field_mm)),), materials={1: "water", 2: "lung"})
    r = simulate(Image(rho, grid), plan,
                 TransportSettings(n, 10, 3, physics=physics, electron_cutoff_mev=0.01),
                 labels=Image(lab, grid), progress=False)
    e = r.energy_per_batch_mev.reshape(10, *grid.shape)[:, :, centre, centre].sum(axis=(2, 3))
    m = r.mass_g.reshape(grid.shape)[:, centre, centre].sum(axis=(1, 2))
    return e / r.histories_per_batch[:, None] / m


def buildup(n: int) -> None:
    spacing = np.array([4.0, 4.0, 1.0])
    grid = ImageGrid(spacing / 2 - [60.0, 60.0, 0.0], spacing, np.eye(3), (30, 30, 40))
    ones, lab = np.ones(grid.shape), np.ones(grid.shape, np.int32)
    k, d = (_layers(ones, lab, grid, 100.0, n, p, slice(12, 18)) for p in ("kerma", "dose"))
    print("2 MeV 100 x 100 mm2 on water: dose/kerma per 1 mm layer (± 1 σ)")
    for z in range(12):
        ratio = d[:, z] / k[:, z].mean()
        print(f"  {z}-{z + 1} mm  {ratio.mean():.3f} ± {ratio.std(ddof=1) / np.sqrt(10):.3f}")
    grid = ImageGrid(spacing / 2 - [50.0, 50.0, 0.0], spacing, np.eye(3), (25, 25, 120))
    lung = np.zeros(grid.shape, bool)
    lung[30:90] = True
    rho, lab = np.where(lung, 0.26, 1.0), np.where(lung, 2, 1).astype(np.int32)
    k, d = (_layers(rho, lab, grid, 30.0, n // 2, p, slice(11, 14)) for p in ("kerma", "dose"))
    ratio = d[:, 45:75].mean(axis=1) / k[:, 45:75].mean()
    print(f"lung 45-75 mm behind 30 mm of water, 30 x 30 mm2: dose/kerma {ratio.mean():.3f} ± "
          f"{ratio.std(ddof=1) / np.sqrt(10):.3f}")


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "buildup":
        buildup(int(float(sys.argv[2])) if len(sys.argv) > 2 else 2_000_000)
        return
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
