"""Bench of the comparison step: gamma on a 512×512×120 grid, resampling, point location, EMT.

Run: ``python bench/bench_compare.py [--full]``. Prints figures; asserts nothing. ``--full``
also evaluates gamma at every point above the threshold (minutes), else only seeded samples.
"""

from __future__ import annotations

import sys
import time

import numpy as np

from tetdose.compare.gamma import gamma_index
from tetdose.core.image import Image, ImageGrid
from tetdose.core.transfer import locate_points, mesh_dose_to_grid
from tetdose.core.voxelize import voxelize
from tetdose.dose.accumulate import energy_mass_transfer
from tetdose.phantoms import make_phantom


def timed(label: str, fn, *args, **kw):  # noqa: ANN001, ANN201
    t = time.perf_counter()
    out = fn(*args, **kw)
    print(f"{label}: {time.perf_counter() - t:.2f} s")
    return out


def big_doses() -> tuple[Image, Image]:
    """A smooth 4-field-like dose on 512×512×120 (0.98×0.98×2.5 mm); evaluated: 1 mm, +2 %."""
    grid = ImageGrid((0, 0, 0), (0.98, 0.98, 2.5), np.eye(3), (512, 512, 120))
    x = (np.arange(512) - 256.0) * 0.98
    z = (np.arange(120) - 60.0) * 2.5

    def field(shift_mm: float) -> np.ndarray:
        fx = 0.5 * (np.tanh((40 - np.abs(x - shift_mm)) / 4) + 1)
        fy = 0.5 * (np.tanh((40 - np.abs(x)) / 4) + 1)
        fz = 0.5 * (np.tanh((50 - np.abs(z)) / 4) + 1)
        body = np.exp(-(x[None, :] ** 2 + x[:, None] ** 2) / 2e4)
        return (fz[:, None, None] * (0.3 * body + fy[:, None] * fx[None, :])[None]).astype(
            np.float32)

    return Image(field(0.0), grid), Image(1.02 * field(1.0), grid)


def bench_gamma(full: bool) -> None:
    ref, ev = timed("build 512×512×120 doses", big_doses)
    n_above = int((ref.array >= 0.1 * ref.array.max()).sum())
    print(f"points above 10 % threshold: {n_above:,} of {ref.array.size:,}")
    gamma_index(ref, ev, max_points=1000)  # warm-up (no JIT; first-touch of arrays)
    for n in (100_000, 1_000_000):
        r = timed(f"gamma 3%/3mm global, {n:,} sampled points", gamma_index, ref, ev,
                  max_points=n)
        print(f"  pass {r.pass_rate_percent:.2f} ± {r.pass_rate_std_percent:.2f} %")
    r = timed("gamma 2%/2mm local, 1,000,000 sampled points", gamma_index, ref, ev,
              dose_percent=2, dta_mm=2, local=True, max_points=1_000_000)
    print(f"  pass {r.pass_rate_percent:.2f} ± {r.pass_rate_std_percent:.2f} %")
    if full:
        r = timed("gamma 3%/3mm global, every point above threshold", gamma_index, ref, ev)
        print(f"  pass {r.pass_rate_percent:.2f} %")


def bench_mesh() -> None:
    t = time.perf_counter()
    ph = make_phantom("thorax", size="small")
    print(f"thorax phantom: {ph.mesh.n_tets} tets, grid {ph.ct.grid.size} "
          f"({time.perf_counter() - t:.2f} s)")
    mesh, grid = ph.mesh, ph.ct.grid
    rho = np.ones(mesh.n_points)
    dose = np.random.default_rng(0).uniform(0, 1, mesh.n_tets)
    timed("mesh_dose_to_grid (first call: overlap JIT/cache load)", mesh_dose_to_grid, mesh,
          dose, grid, density_g_cm3=rho)
    timed("mesh_dose_to_grid", mesh_dose_to_grid, mesh, dose, grid, density_g_cm3=rho)
    pts = grid.voxel_centers_mm()
    t = time.perf_counter()
    locate_points(mesh, pts)
    dt = time.perf_counter() - t
    print(f"locate_points: {len(pts):,} points in {dt:.2f} s ({len(pts) / dt:,.0f} points/s)")
    density = voxelize(mesh, rho, grid)
    phase = mesh.points_mm + np.array([0.0, 0.0, 5.0])
    timed("energy/mass transfer, 1 phase, 2×2×2 sub-voxels", energy_mass_transfer, mesh,
          phase[None], [Image(np.ones(grid.shape), grid)], [density], grid)


if __name__ == "__main__":
    bench_mesh() if "--no-mesh" not in sys.argv else None
    bench_gamma("--full" in sys.argv)
