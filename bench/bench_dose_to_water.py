"""Dose to water from the tracked electron fluence (issue 32): the fluence-averaged s_w,m of
homogeneous worlds under the 6 MV spectrum against the per-medium table and Siebers et al.
(PMB 45:983, 2000: cortical bone ≈ 1.11, soft tissue 1.00–1.02, lung ≈ 1.00), and what the
tally costs.

Run: ``NUMBA_CACHE_DIR=.numba-cache python bench/bench_dose_to_water.py [--histories 3000]
[--cost-histories 400000]``. The worlds are 40 mm cubes (8 mm voxels, or 2 × 2 × 4 boxes of
tets) of one medium at its density, the beam parallel, 30 × 30 mm². Printed per world: the
tracked Σ A / Σ B, the table's s_w,m, and the cells with dose that fell back to the table.
The cost: CPU time of the same run with dose to medium and to water, alternated three times in
this process (2 mm voxels of bone / soft tissue / lung), the median ratio.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from tetdose.core.image import Image
from tetdose.core.mesh import TetMesh
from tetdose.plan.spectra import named_spectrum
from tetdose.transport import PhotonSource, Plan, TransportSettings, World, simulate
from tetdose.transport.physics.dose_to_water import water_to_medium_ratio

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from helpers import box_mesh, density_image, grid_for  # noqa: E402

MEDIA = {"icrp_cortical_bone": 1.85, "soft_tissue": 1.06, "lung": 0.26}


def _beam() -> PhotonSource:
    e, w = named_spectrum("6MV")
    return PhotonSource("parallel", [0.0, 0.0, -40.0], [0, 0, 1], energies_mev=e, line_weights=w,
                        field_mm=[30.0, 30.0])


def _world(geometry: str, rho: float, spacing_mm: float = 8.0) -> World:
    if geometry == "voxels":
        grid = grid_for([-20, -20, -20], [20, 20, 20], [spacing_mm] * 3)
        return World(density=density_image(grid, lambda x, y, z: np.full(x.shape, rho)),
                     labels=Image(np.ones(grid.shape, np.int32), grid))
    mesh = box_mesh([-20, -20, -20], [20, 20, 20], (2, 2, 4))
    return World(mesh=TetMesh(mesh.points_mm, mesh.tets, np.ones(mesh.n_tets, np.int32),
                              {"density": np.full(mesh.n_points, rho)}))


def ratios(histories: int) -> None:
    print(f"{'world':8s} {'medium':20s} {'tracked':>8s} {'table':>8s}  fallback")
    for geometry in ("voxels", "tets"):
        for medium, rho in MEDIA.items():
            r = simulate(_world(geometry, rho), Plan((_beam(),), materials={1: medium}),
                         TransportSettings(histories, 4, 7, dose_to="water"), progress=False)
            rec = r.extra["dose_to_water"]
            s = next(iter(rec["s_w_m"].values()))
            print(f"{geometry:8s} {medium:20s} {s:8.4f} {water_to_medium_ratio(medium):8.4f}  "
                  f"{rec['cells_fallback']} of {rec['cells_dosed']}", flush=True)


def cost(histories: int) -> None:
    grid = grid_for([-20, -20, -20], [20, 20, 20], [2.0, 2.0, 2.0])
    world = World(density=density_image(
        grid, lambda x, y, z: np.where(z > 0, 1.85, np.where(z < -8, 0.26, 1.0))))
    cpu: dict[str, list[float]] = {"medium": [], "water": []}
    for _ in range(3):
        for to in cpu:
            r = simulate(world, Plan((_beam(),)), TransportSettings(histories, 10, 5, dose_to=to),
                         progress=False)
            cpu[to].append(r.extra["cpu_s"])
    print(f"CPU s, medium {cpu['medium']}, water {cpu['water']}: water / medium "
          f"{np.median(cpu['water']) / np.median(cpu['medium']):.3f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--histories", type=int, default=3000)
    ap.add_argument("--cost-histories", type=int, default=400_000)
    args = ap.parse_args()
    ratios(args.histories)
    cost(args.cost_histories)


if __name__ == "__main__":
    main()
