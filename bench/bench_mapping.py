"""Density-mapping benchmarks: exact vs Monte Carlo overlap, a large organ, real CT figures.

Run: ``NUMBA_CACHE_DIR=... .venv/bin/python bench/bench_mapping.py {mc,large,real} [options]``

- ``mc``: exact clipping vs the paper's hit-and-miss estimate at equal accuracy. The error of F
  (F_kj = Vol(T_k ∩ V_j)/Vol(T_k), eq. 7) is |F_mc − F_exact| over every pair either method
  finds, in units of F (1 % = 0.01), as an RMS and as a maximum; for each, n_samples is doubled
  until the error is ≤ 1 %, then bisected on a log scale; both methods are timed and the
  ratio printed.
- ``large``: a ~100 000-tetrahedron ellipsoidal organ (liver-sized) on a 512×512×120 CT
  (0.977×0.977×2 mm); ``map_density`` timed with NUMBA_NUM_THREADS=1 and 2, each in a fresh
  subprocess (warm-up on a small case first, compile/load time printed separately). Peak memory
  is the rise of the process's peak RSS during the call (VmHWM reset through
  /proc/self/clear_refs), compared with pairs × 48 B and with the CT grid's size.
- ``real``: the paper's Table II–III metrics on the real CT in ../shared/data (lung and liver):
  RMDE, ESD, mass errors for "l2" vs "lsq", exact vs Monte Carlo overlap, and the two-region
  (lung + chest wall) mesh with and without ``by_region``. The meshes are organ-shaped
  (``tetdose.meshing.conforming_mesh`` of the label image at its own resolution, MMG; the
  lung + chest wall one conforming across the lung surface); a staircase row per size
  (``mesh_labels`` of the labels on the CT grid, the earlier figures) is kept as the reference.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

from tetdose.core.image import Image, ImageGrid
from tetdose.core.mesh import TetMesh
from tetdose.core.overlap import compute_overlap
from tetdose.mapping import map_density
from tetdose.phantoms import make_phantom, mesh_labels

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"
PAIR_BYTES = 48  # voxel id 8 + 4 barycentric moments 32 + cached tet id 8
TARGET_F_RMS = 0.01


def best_of(fn, repeats: int = 3) -> float:  # noqa: ANN001
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


# --------------------------------------------------------------------------- exact vs MC


def f_errors(mesh: TetMesh, exact, mc) -> tuple[float, float]:  # noqa: ANN001
    """(RMS, max) of |F_mc − F_exact| over the union of both supports (F in [0, 1])."""
    a, b = exact.volume_matrix_mm3(), mc.volume_matrix_mm3()
    diff = (b - a).tocoo()
    f = np.abs(diff.data) / mesh.volumes_mm3[diff.row]
    return float(np.sqrt(np.sum(f**2) / (a + b).nnz)), float(f.max(initial=0.0))


def samples_for(err, which: int) -> int:  # noqa: ANN001
    """Smallest n_samples (doubling, then 4 log-bisection steps) with err(n)[which] ≤ 1 %."""
    n = 16
    while err(n)[which] > TARGET_F_RMS:
        n *= 2
    lo, hi = n // 2, n
    for _ in range(4):
        mid = int(round(np.sqrt(lo * hi)))
        if mid in (lo, hi):
            break
        lo, hi = (mid, hi) if err(mid)[which] > TARGET_F_RMS else (lo, mid)
    return hi


def bench_mc(args: argparse.Namespace) -> None:
    ph = make_phantom("liver", seed=0, size="small")
    grid = ph.ct.grid
    mesh = TetMesh(ph.mesh.points_mm, ph.mesh.tets[:: max(1, ph.mesh.n_tets // args.tets)])
    t0 = time.perf_counter()
    exact = compute_overlap(mesh, grid)
    compute_overlap(mesh, grid, method="monte-carlo", n_samples=16)
    print(f"warm-up (compile/load) {time.perf_counter() - t0:.2f} s")
    edge_vox = np.cbrt(6 * mesh.volumes_mm3.mean()) / grid.spacing_mm.mean()
    print(f"{mesh.n_tets} tets of the liver phantom (small), grid {grid.size} at "
          f"{grid.spacing_mm[0]:g} mm, cube edge ≈ {edge_vox:.1f} voxels, "
          f"{exact.n_pairs} pairs ({exact.n_pairs / mesh.n_tets:.1f} per tet)")
    cache: dict[int, tuple[float, float]] = {}

    def err(n: int) -> tuple[float, float]:
        if n not in cache:
            mc = compute_overlap(mesh, grid, method="monte-carlo", n_samples=n, seed=1)
            cache[n] = f_errors(mesh, exact, mc)
        return cache[n]

    found = {name: samples_for(err, i) for i, name in enumerate(("RMS", "max"))}
    print(f"{'n_samples':>10} {'RMS |ΔF|':>10} {'max |ΔF|':>10}")
    for n in sorted(cache):
        print(f"{n:>10} {cache[n][0]:10.3%} {cache[n][1]:10.3%}")
    t_exact = best_of(lambda: compute_overlap(mesh, grid))
    print(f"\nexact overlap: {t_exact * 1e3:.1f} ms ({t_exact / mesh.n_tets * 1e6:.0f} µs/tet)")
    for name, n in found.items():
        t_mc = best_of(lambda n=n: compute_overlap(mesh, grid, method="monte-carlo",
                                                   n_samples=n, seed=1), repeats=2)
        print(f"{name} |ΔF| ≤ 1 %: n_samples = {n:>6}; Monte Carlo {t_mc * 1e3:9.1f} ms; "
              f"MC / exact = {t_mc / t_exact:6.1f}×  (target ≥ 20×)")


# --------------------------------------------------------------------------- large organ


def large_case(n_tets_target: int = 100_000) -> tuple[TetMesh, Image]:
    """Ellipsoidal organ (semi-axes 90×70×60 mm, ~1.6 L) meshed to ~n_tets_target tets, on a
    512×512×120 CT of 0.977×0.977×2 mm (organ ≈ 55 ± 15 HU, seeded noise; fat around, air out).
    """
    spacing = np.array([0.9765625, 0.9765625, 2.0])
    size = (512, 512, 120)
    origin = -0.5 * (np.array(size) - 1) * spacing
    grid = ImageGrid(origin, spacing, np.eye(3), size)
    semi = np.array([90.0, 70.0, 60.0])
    # Mesh a 2 mm label image of the organ (the mesher works in patient coordinates).
    lab_sp = 2.0
    lab_size = tuple(int(n) for n in np.ceil(2.2 * semi / lab_sp))
    lab_grid = ImageGrid(-0.5 * (np.array(lab_size) - 1) * lab_sp, np.full(3, lab_sp), np.eye(3),
                         lab_size)
    c = lab_grid.voxel_centers_mm()
    inside = (np.sum((c / semi) ** 2, axis=1) <= 1.0).reshape(lab_grid.shape)
    volume = 4 / 3 * np.pi * semi.prod()
    edge = float(np.cbrt(6 * volume / n_tets_target))
    mesh = mesh_labels(Image(inside.astype(np.uint8), lab_grid), [1], edge)
    k, j, i = np.ogrid[: size[2], : size[1], : size[0]]
    r2 = (((i * spacing[0] + origin[0]) / semi[0]) ** 2 + ((j * spacing[1] + origin[1]) / semi[1]) ** 2
          + ((k * spacing[2] + origin[2]) / semi[2]) ** 2)
    rng = np.random.default_rng(0)
    hu = np.where(r2 <= 1.05, 55.0, np.where(r2 <= 2.5, -100.0, -1000.0)).astype(np.float32)
    hu += rng.normal(0.0, 15.0, hu.shape).astype(np.float32)
    return mesh, Image(np.rint(hu).astype(np.int16), grid)


def _rss_kb(field: str) -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    return -1


def measure(fn) -> tuple[float, float, object]:  # noqa: ANN001
    """(seconds, peak RSS rise [MB], result) of fn() — VmHWM reset before the call."""
    Path("/proc/self/clear_refs").write_text("5")
    base = _rss_kb("VmRSS")
    t0 = time.perf_counter()
    out = fn()
    dt = time.perf_counter() - t0
    return dt, (_rss_kb("VmHWM") - base) / 1024.0, out


def worker(task: str, case: str) -> None:
    """Run in a subprocess: warm up, then time ``task`` (map | voxelize) on the saved case."""
    from tetdose.core.voxelize import voxelize

    data = np.load(case)
    grid = ImageGrid(data["origin"], data["spacing"], np.eye(3), tuple(data["size"]))
    mesh, ct = TetMesh(data["points"], data["tets"]), Image(data["hu"], grid)
    t0 = time.perf_counter()
    small = make_phantom("liver", seed=0, size="small")
    warm = map_density(small.mesh, small.ct)
    voxelize(warm.mesh, warm.density_g_cm3, small.ct.grid)
    compile_s = time.perf_counter() - t0
    if task == "map":
        dt, peak_mb, dm = measure(lambda: map_density(mesh, ct))
        pairs = dm.overlap.n_pairs
    else:
        rho = data["density"]
        ov = compute_overlap(mesh, grid)
        pairs = ov.n_pairs
        del ov
        dt, peak_mb, _ = measure(lambda: voxelize(mesh, rho, grid))
    print(json.dumps({"compile_s": compile_s, "seconds": dt, "peak_mb": peak_mb,
                      "pairs": pairs, "n_voxels": grid.n_voxels}))


def run_scaling(task: str, mesh: TetMesh, ct: Image, density: np.ndarray | None = None) -> None:
    """Time ``task`` in fresh subprocesses with 1 and 2 numba threads and print the table."""
    with tempfile.TemporaryDirectory() as tmp:
        case = Path(tmp) / "case.npz"
        g = ct.grid
        np.savez(case, points=mesh.points_mm, tets=mesh.tets, hu=ct.array, origin=g.origin_mm,
                 spacing=g.spacing_mm, size=np.array(g.size),
                 density=density if density is not None else np.zeros(0))
        res = {}
        for threads in (1, 2):
            env = {**os.environ, "NUMBA_NUM_THREADS": str(threads),
                   "OPENBLAS_NUM_THREADS": "1"}
            out = subprocess.run([sys.executable, __file__, "_worker", task, str(case)], env=env,
                                 check=True, capture_output=True, text=True)
            res[threads] = json.loads(out.stdout.strip().splitlines()[-1])
    r1, r2 = res[1], res[2]
    pairs_mb = r1["pairs"] * PAIR_BYTES / 2**20
    grid_mb = r1["n_voxels"] * 8 / 2**20
    print(f"{task}: {mesh.n_tets} tets, {mesh.n_points} points, CT {ct.grid.size} "
          f"({r1['n_voxels'] / 1e6:.1f} M voxels), {r1['pairs']} tet–voxel pairs")
    print(f"{'threads':>8} {'compile/load s':>15} {'time s':>8} {'peak RSS rise MB':>17}")
    for t in (1, 2):
        print(f"{t:>8} {res[t]['compile_s']:15.2f} {res[t]['seconds']:8.2f} "
              f"{res[t]['peak_mb']:17.0f}")
    print(f"scaling 1 → 2 threads: {r1['seconds'] / r2['seconds']:.2f}×  (machine load average "
          f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs: other processes skew this)")
    print(f"pairs × {PAIR_BYTES} B = {pairs_mb:.0f} MB; one float64 CT-sized array = "
          f"{grid_mb:.0f} MB; peak / (pairs × {PAIR_BYTES} B) = {r1['peak_mb'] / pairs_mb:.2f}")


def bench_large(args: argparse.Namespace) -> None:
    t0 = time.perf_counter()
    mesh, ct = large_case(args.tets)
    print(f"case built in {time.perf_counter() - t0:.1f} s")
    run_scaling("map", mesh, ct)


# --------------------------------------------------------------------------- real CT


def bench_real(args: argparse.Namespace) -> None:
    sys.path.insert(0, str(ROOT / "tests" / "verification"))
    sys.path.insert(0, str(ROOT / "tests"))
    import test_real_ct as rc  # the test module's loaders: one definition of the real cases

    from tetdose.mapping.metrics import evaluate
    from tetdose.meshing import conforming_mesh

    if not SHARED.is_dir():
        sys.exit(f"{SHARED} not found: the real CT lives in ../shared/data")
    ct_l = rc.read_image(rc.LUNG_CT)
    mask_l = rc.read_image(rc.LUNG_MASK)
    lab_l = rc.resample_labels(mask_l, ct_l.grid)
    ct_a = rc.read_image(rc.ABDOMEN_CT)
    seg = rc.read_image(rc.ABDOMEN_SEG)
    lab_a = rc.resample_labels(seg, ct_a.grid)
    two = lab_l.array.copy()
    two[(two == 0) & (ct_l.array > rc.BODY_HU)] = 2
    # (name, CT, labels on the CT grid (staircase), labels at their own resolution (organ), ROI, ids)
    cases = [("lung", ct_l, lab_l, mask_l, lab_l.array == 1, [1], e) for e in args.lung_edges]
    cases += [("liver", ct_a, lab_a, seg, lab_a.array == rc.LIVER, [rc.LIVER], e)
              for e in args.liver_edges]
    print(f"{'case':<30}{'tets':>8} {'mesh s':>6} {'solver':>6} {'overlap':>7} {'RMDE %':>8} "
          f"{'ESD %':>8} {'median %':>8} {'eq.23 %':>8} {'in-mesh mass err':>16} {'map s':>6}")

    def row(name: str, mesh: TetMesh, mesh_s: float, ct: Image, roi: np.ndarray,
            **kw: object) -> None:
        t0 = time.perf_counter()
        with warnings.catch_warnings():  # a smooth surface pokes < 0.01 % out of a tight CT
            warnings.filterwarnings("ignore", message=".*lies outside the image")
            dm = map_density(mesh, ct, **kw)
        exact = dm.overlap if dm.overlap.method == "exact" else None
        ev = evaluate(ct, dm.mesh, dm.density_g_cm3, roi=roi, overlap=exact)
        dt = time.perf_counter() - t0
        m = ev.metrics
        med = float(np.median(ev.relative_error_pct.array[roi]))
        ov = "MC" if kw.get("overlap") == "monte-carlo" else "exact"
        print(f"{name:<30}{mesh.n_tets:>8} {mesh_s:6.1f} {dm.solver:>6} {ov:>7} {m.rmde_pct:8.2f} "
              f"{m.esd_pct:8.2f} {med:8.2f} {m.mass_error_pct:8.2f} "
              f"{dm.mass_error_covered:16.1e} {dt:6.1f}", flush=True)

    def timed(fn):  # noqa: ANN001, ANN202
        t0 = time.perf_counter()
        return fn(), time.perf_counter() - t0

    for name, ct, on_grid, own, roi, ids, edge in cases:
        mesh, mesh_s = timed(lambda on_grid=on_grid, ids=ids, e=edge: mesh_labels(on_grid, ids, e))
        row(f"{name} {edge:g} mm staircase", mesh, mesh_s, ct, roi, solver="l2")
        mesh, mesh_s = timed(lambda own=own, ids=ids, e=edge: conforming_mesh(own, ids, e))
        label = f"{name} {edge:g} mm organ-shaped"
        for solver in ("l2", "lsq"):
            row(label, mesh, mesh_s, ct, roi, solver=solver)
        row(label, mesh, mesh_s, ct, roi, solver="l2", overlap="monte-carlo",
            n_samples=args.mc_samples)
    roi = two == 1
    for label, fn in (("lung+wall 10 mm staircase", lambda: mesh_labels(Image(two, ct_l.grid),
                                                                          [1, 2], 10.0)),
                      ("lung+wall 10 mm organ-shaped",
                       lambda: conforming_mesh(Image(two, ct_l.grid), [1, 2], 10.0))):
        mesh, mesh_s = timed(fn)
        row(f"{label}, joint", mesh, mesh_s, ct_l, roi)
        row(f"{label}, by_region", mesh, mesh_s, ct_l, roi, by_region=True)


def main() -> None:
    if len(sys.argv) == 4 and sys.argv[1] == "_worker":
        worker(sys.argv[2], sys.argv[3])
        return
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="what", required=True)
    p = sub.add_parser("mc", help="exact vs Monte Carlo overlap at equal accuracy")
    p.add_argument("--tets", type=int, default=500, help="tetrahedra taken from the phantom")
    p = sub.add_parser("large", help="~100k-tet organ on a 512×512×120 CT, 1 vs 2 threads")
    p.add_argument("--tets", type=int, default=100_000)
    p = sub.add_parser("real", help="paper metrics on the real lung and liver CT")
    p.add_argument("--lung-edges", type=float, nargs="*", default=[10.0, 5.0])
    p.add_argument("--liver-edges", type=float, nargs="*", default=[8.0, 4.0])
    p.add_argument("--mc-samples", type=int, default=1000)
    args = parser.parse_args()
    {"mc": bench_mc, "large": bench_large, "real": bench_real}[args.what](args)


if __name__ == "__main__":
    main()
