"""Transport speed: tet crossings/s (pure walk), photons/s and crossings/s with physics, mesh vs
voxel time per history, 1 → 2 thread scaling against the machine's own, time to 1 % uncertainty
(analog vs track-length).

Run: ``NUMBA_CACHE_DIR=... .venv/bin/python bench/bench_transport.py [SIZES] [HISTORIES]``, SIZES
a comma list of cubes per axis (default ``10,20,30,40``; the last one is the main case).
A 200 mm water box of n³ cubes (6 tets each: 6 k, 48 k, 162 k, 384 k tets) and the matching n³
voxel grid (matched resolution: each voxel is exactly 6 tets); a 1.25 MeV 100 × 100 mm² parallel
field along z; last, the pure walk on the demo's thorax phantom mesh. The pure walk is timed with
and without the boundary ray cast that brings each ray into the mesh (MMC's figure is the walk:
its photons start inside). The first call of every kernel is a warm-up whose time is reported as
compile/load time. Single-thread figures are the best of several runs in CPU time
(``time.process_time``), which other jobs on a shared machine disturb less than wall time;
thread scaling needs wall time, so it is repeated, the spread printed, and set against the
scaling of a pure-arithmetic numba kernel measured in the same process (what this machine's two
cores give at best). Run-to-run spread on the shared VM is large (±30 % seen): run it twice.
"""

from __future__ import annotations

import itertools
import os
import sys
import time

import numba
import numpy as np
from numba import njit, prange

from tetdose.core.image import Image, ImageGrid
from tetdose.core.mesh import TetMesh
from tetdose.phantoms import make_phantom
from tetdose.transport import (
    PhotonSource,
    Plan,
    TransportSettings,
    mesh_geometry,
    morton_order,
    simulate,
)
from tetdose.transport.geometry._tet import enter_mesh, exit_face, next_tet, prefetch_neighbours

PLAN = Plan((PhotonSource("parallel", [0, 0, -150.0], [0, 0, 1], energies_mev=[1.25],
                          field_mm=[100.0, 100.0]),))


def box(n: int, size_mm: float = 200.0) -> tuple[TetMesh, Image]:
    ax = np.linspace(-size_mm / 2, size_mm / 2, n + 1)
    pts = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    vid = lambda i, j, k: (i * (n + 1) + j) * (n + 1) + k  # noqa: E731
    tets = []
    for c0 in itertools.product(range(n), repeat=3):
        for perm in itertools.permutations(range(3)):
            c = list(c0)
            path = [vid(*c)]
            for a in perm:
                c[a] += 1
                path.append(vid(*c))
            tets.append(path)
    mesh = TetMesh(pts, np.array(tets)).with_fixed_orientation()
    mesh = mesh.with_data(point_data={"density": np.ones(len(pts))})
    h = size_mm / n
    grid = ImageGrid(np.full(3, -size_mm / 2 + h / 2), np.full(3, h), np.eye(3), (n, n, n))
    return mesh, Image(np.ones(grid.shape), grid)


@njit(cache=True)
def _walk_rays(g, starts, dirs):
    """Pure-absorber walk (no physics): count tetrahedron crossings of all rays."""
    crossings = 0
    no_tally = np.empty(0)
    for r in range(starts.shape[0]):
        u, v, w = dirs[r, 0], dirs[r, 1], dirs[r, 2]
        k, x, y, z, _ = enter_mesh(g, starts[r, 0], starts[r, 1], starts[r, 2], u, v, w)
        entry = -1
        while k >= 0:
            prefetch_neighbours(g, k, entry, False, no_tally)
            f, t = exit_face(g, k, x, y, z, u, v, w, entry)
            if f < 0:
                break
            x, y, z = x + t * u, y + t * v, z + t * w
            k, entry = next_tet(g, k, f)
            crossings += 1
    return crossings


@njit(cache=True)
def _enter_rays(g, starts, dirs):
    """Entry only (boundary ray cast): the part of :func:`_walk_rays` that is not walking."""
    entered = 0
    for r in range(starts.shape[0]):
        k, _, _, _, _ = enter_mesh(g, starts[r, 0], starts[r, 1], starts[r, 2],
                                   dirs[r, 0], dirs[r, 1], dirs[r, 2])
        entered += k >= 0
    return entered


def _best_cpu(fn, *args, repeat: int = 5):  # noqa: ANN001, ANN202
    best, out = np.inf, None
    for _ in range(repeat):
        t0 = time.process_time()
        out = fn(*args)
        best = min(best, time.process_time() - t0)
    return out, best


def bench_walk(mesh: TetMesh, all_orders: bool) -> None:
    rng = np.random.default_rng(0)
    n = 20000
    lo, hi = mesh.points_mm.min(axis=0), mesh.points_mm.max(axis=0)
    centre, half = (lo + hi) / 2, (hi - lo) / 2
    # beam: from below the mesh, nearly along z, over the central 90 % of its x–y extent
    beam = (np.column_stack([centre[:2] + rng.uniform(-0.9, 0.9, (n, 2)) * half[:2],
                             np.full(n, lo[2] - 50.0)]),
            rng.normal(size=(n, 3)) * [0.2, 0.2, 0.0] + [0, 0, 1.0])
    # isotropic: from a sphere around the mesh towards random points inside its box
    aim = centre + rng.uniform(-0.95, 0.95, (n, 3)) * half
    out = rng.normal(size=(n, 3))
    out *= 1.1 * np.linalg.norm(half) / np.linalg.norm(out, axis=1, keepdims=True)
    iso = (centre + out, aim - centre - out)
    orders = {"Morton": morton_order(mesh.centroids_mm)}
    if all_orders:
        orders |= {"as built (z fastest)": None, "random": rng.permutation(mesh.n_tets)}
    for name, order in orders.items():
        g = mesh_geometry(mesh, mesh.point_data["density"], np.zeros(mesh.n_tets, np.intp), order)
        for rays, (starts, dirs) in (("beam rays", beam), ("isotropic rays", iso)):
            dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
            t0 = time.perf_counter()
            _walk_rays(g, starts[:1], dirs[:1])
            _enter_rays(g, starts[:1], dirs[:1])
            compile_s = time.perf_counter() - t0
            count, cpu = _best_cpu(_walk_rays, g, starts, dirs)
            _, entry_cpu = _best_cpu(_enter_rays, g, starts, dirs)
            print(f"  pure walk, {mesh.n_tets:7d} tets {name:20s} {rays:14s}: "
                  f"{count / (cpu - entry_cpu) / 1e6:5.1f} M crossings/s walking, "
                  f"{count / cpu / 1e6:5.1f} incl. entry ({entry_cpu / len(starts) * 1e6:.2f} µs/ray;"
                  f" {count / len(starts):.0f} crossings/ray; 1 core; compile/load {compile_s:.1f} s)")


def bench_transport(mesh: TetMesh, image: Image, n_hist: int, repeat: int = 3) -> None:
    numba.set_num_threads(1)
    per_history = {}
    for geom, name in ((mesh, "mesh"), (image, "voxel")):
        t0 = time.perf_counter()
        simulate(geom, PLAN, TransportSettings(20, 2, physics="kerma"), progress=False)
        compile_s = time.perf_counter() - t0
        for est in ("track_length", "analog"):
            settings = TransportSettings(n_hist, 10, estimator=est, physics="kerma")
            runs = [simulate(geom, PLAN, settings, progress=False) for _ in range(repeat)]
            r = min(runs, key=lambda run: run.extra["cpu_s"])
            cpu = r.extra["cpu_s"]
            per_history[name, est] = cpu / n_hist
            extra = (f", {r.crossings / cpu / 1e6:4.1f} M crossings/s "
                     f"({r.crossings / n_hist:.0f} per history)" if name == "mesh" else "")
            print(f"  {name:5s} {est:12s}: {n_hist / cpu:8.0f} photons/s, "
                  f"{cpu / n_hist * 1e6:6.2f} µs/history{extra} (1 core; compile/load "
                  f"{compile_s:.1f} s)")
    ratio = per_history["mesh", "track_length"] / per_history["voxel", "track_length"]
    print(f"  mesh / voxel time per history (track-length): {ratio:.1f}×")


def bench_ceiling(repeat: int = 3) -> float:
    """1 → 2 thread speed-up of a pure-arithmetic kernel: what the machine's cores give at best."""
    if numba.config.NUMBA_NUM_THREADS < 2:
        return 1.0
    _arithmetic(10)
    walls: dict[int, list[float]] = {1: [], 2: []}
    for _ in range(repeat):
        for threads in (1, 2):
            numba.set_num_threads(threads)
            t0 = time.perf_counter()
            _arithmetic(20_000_000)
            walls[threads].append(time.perf_counter() - t0)
    speedup = min(walls[1]) / min(walls[2])
    print(f"machine: pure-arithmetic numba kernel 1 → 2 threads {speedup:.2f}× "
          f"(load average {os.getloadavg()[0]:.1f})")
    return speedup


@njit(cache=True, parallel=True)
def _arithmetic(n):
    """Eight independent recurrences, one per prange iteration (no memory traffic)."""
    out = np.zeros(8)
    for b in prange(8):
        x, s = 1.0 + b, 0.0
        for _ in range(n):
            x = x * 1.0000001 + 1e-9
            s += 1.0 / x
        out[b] = s
    return out


def bench_threads(mesh: TetMesh, n_hist: int, ceiling: float, repeat: int = 3) -> None:
    if numba.config.NUMBA_NUM_THREADS < 2:
        print("thread scaling: only one thread available")
        return
    walls: dict[int, list[float]] = {1: [], 2: []}
    settings = TransportSettings(n_hist, 8, physics="kerma")
    for _ in range(repeat):
        for threads in (1, 2):
            numba.set_num_threads(threads)
            walls[threads].append(simulate(mesh, PLAN, settings, progress=False).wall_s)
    ratios = np.array(walls[1]) / np.array(walls[2])
    speedup = min(walls[1]) / min(walls[2])
    print(f"  mesh transport 1 → 2 threads ({repeat} pairs, wall): 1 thread {min(walls[1]):.2f}–"
          f"{max(walls[1]):.2f} s, 2 threads {min(walls[2]):.2f}–{max(walls[2]):.2f} s; "
          f"speed-up {speedup:.2f}× (best/best; pairs {ratios.min():.2f}–{ratios.max():.2f}×), "
          f"{speedup / ceiling:.0%} of the machine's {ceiling:.2f}×")


def bench_uncertainty(mesh: TetMesh, image: Image, n_hist: int) -> None:
    """Time to 1 % relative uncertainty of the energy in a target region, σ ∝ 1/√N."""
    numba.set_num_threads(1)
    regions = {"on axis, depth 100 mm": (0.0, 0.0, 0.0), "off beam, x = 80 mm": (80.0, 0.0, 0.0)}
    print("time to 1 % uncertainty in a 20 mm-radius sphere (1 thread, CPU time):")
    print(f"  {'region':24s} {'geometry':8s} {'analog':>10s} {'track-length':>13s}")
    for geom, name, centres in ((mesh, "mesh", mesh.centroids_mm),
                                (image, "voxel", image.grid.voxel_centers_mm())):
        times = {r: [] for r in regions}
        for est in ("analog", "track_length"):
            res = simulate(geom, PLAN, TransportSettings(n_hist, 20, estimator=est, physics="kerma"),
                           progress=False)
            cpu = res.extra["cpu_s"]
            x = res.energy_per_batch_mev / res.histories_per_batch[:, None]
            for reg, c in regions.items():
                sel = np.linalg.norm(centres - np.array(c), axis=1) < 20.0
                e = x[:, sel].sum(axis=1)
                rel = e.std(ddof=1) / np.sqrt(len(e)) / e.mean()
                times[reg].append(cpu * (rel / 0.01) ** 2)
        for reg, (ta, tt) in times.items():
            print(f"  {reg:24s} {name:8s} {ta:9.1f}s {tt:12.1f}s")


if __name__ == "__main__":
    sizes = [int(a) for a in (sys.argv[1] if len(sys.argv) > 1 else "10,20,30,40").split(",")]
    n_hist = int(float(sys.argv[2])) if len(sys.argv) > 2 else 100_000
    print(f"{numba.config.NUMBA_NUM_THREADS} threads available, "
          f"load average {os.getloadavg()[0]:.1f}")
    ceiling = bench_ceiling()
    for n_cubes in sizes:
        mesh, image = box(n_cubes)
        main = n_cubes == sizes[-1]
        print(f"water box 200 mm, {n_cubes}³ cubes: {mesh.n_tets} tets / {image.grid.n_voxels} "
              f"voxels")
        bench_walk(mesh, all_orders=main)
        bench_transport(mesh, image, n_hist)
        bench_threads(mesh, n_hist, ceiling)
    bench_uncertainty(mesh, image, n_hist // 2)
    thorax = make_phantom("thorax").mesh
    thorax = thorax.with_data(point_data={"density": np.ones(thorax.n_points)})
    print(f"demo thorax phantom mesh (unstructured, conforming regions): {thorax.n_tets} tets, "
          f"water density")
    bench_walk(thorax, all_orders=False)
