"""The density-mapping paper's preliminary experiment (§IV.C.1, Figs. 11–12) on the ``cube`` phantom.

Run: ``NUMBA_CACHE_DIR=... .venv/bin/python bench/bench_paper_cube.py [OUT_DIR] [--seeds N]``
(default ``bench-out/``). For n = 3…10 (σ = 50 HU) and for σ = 10…200 HU (n = 5), maps
``--seeds`` seeded n×n×n images of N(50 HU, σ²) with the same 20-tetrahedron, 18-vertex mesh,
prints mean ± sd over the seeds of the RMDE (eq. 24–25), the ESD (eq. 26) and the mass error
(eq. 23) for the "l2" and "lsq" solvers, and saves ``cube_rmde_vs_n.png`` and
``cube_rmde_vs_std.png`` into OUT_DIR.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from tetdose.mapping import map_density
from tetdose.mapping.metrics import evaluate
from tetdose.phantoms import make_phantom

SIZES = tuple(range(3, 11))
STDS_HU = (10.0, 25.0, 50.0, 100.0, 150.0, 200.0)
SOLVERS = ("l2", "lsq")


def cube_metrics(n: int, std_hu: float, seed: int, solver: str) -> tuple[float, float, float]:
    """(RMDE %, ESD %, mass error %) of one cube image."""
    ph = make_phantom("cube", seed=seed, n=n, std_hu=std_hu)
    dm = map_density(ph.mesh, ph.ct, solver=solver)
    m = evaluate(ph.ct, dm.mesh, dm.density_g_cm3, overlap=dm.overlap).metrics
    return m.rmde_pct, m.esd_pct, m.mass_error_pct


def sweep(points: list[tuple[int, float]], seeds: int) -> dict[str, np.ndarray]:
    """{solver: (len(points), seeds, 3) array of cube_metrics}."""
    return {s: np.array([[cube_metrics(n, sd, seed, s) for seed in range(seeds)]
                         for n, sd in points]) for s in SOLVERS}


def print_table(title: str, label: str, xs: list[float], res: dict[str, np.ndarray]) -> None:
    print(f"\n{title}")
    print(f"{label:>6} | " + " | ".join(f"{s:>3}: RMDE % (sd)   ESD %   mass err %" for s in SOLVERS))
    for i, x in enumerate(xs):
        cells = []
        for s in SOLVERS:
            r = res[s][i]
            cells.append(f"{r[:, 0].mean():8.3f} ({r[:, 0].std():.3f}) {r[:, 1].mean():7.3f}"
                         f" {r[:, 2].max():11.2e}")
        print(f"{x:>6g} | " + " | ".join(cells))


def plot(path: Path, xs: list[float], res: dict[str, np.ndarray], xlabel: str, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.6), constrained_layout=True)
    for s, marker in zip(SOLVERS, "os", strict=True):
        r = res[s][:, :, 0]
        ax.errorbar(xs, r.mean(axis=1), yerr=r.std(axis=1), marker=marker, capsize=3,
                    label=f"solver={s}")
    ax.set_xlabel(xlabel)
    ax.set_ylabel("relative mean density error RMDE [%]")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out_dir", nargs="?", default="bench-out")
    parser.add_argument("--seeds", type=int, default=20)
    args = parser.parse_args()
    out = Path(args.out_dir)
    out.mkdir(parents=True, exist_ok=True)

    t0 = time.perf_counter()
    cube_metrics(5, 50.0, 0, "l2")  # warm-up: numba compile or cache load
    print(f"warm-up (compile/load) {time.perf_counter() - t0:.2f} s")
    t0 = time.perf_counter()
    by_n = sweep([(n, 50.0) for n in SIZES], args.seeds)
    by_sd = sweep([(5, sd) for sd in STDS_HU], args.seeds)
    elapsed = time.perf_counter() - t0
    print_table(f"RMDE vs image size n (σ = 50 HU, mean over {args.seeds} seeds) — paper Fig. 11",
                "n", list(SIZES), by_n)
    print_table(f"RMDE vs image σ (n = 5, mean over {args.seeds} seeds) — paper Fig. 12",
                "σ HU", list(STDS_HU), by_sd)
    plot(out / "cube_rmde_vs_n.png", list(SIZES), by_n, "image size n (n×n×n voxels)",
         "cube phantom, σ = 50 HU (paper Fig. 11)")
    plot(out / "cube_rmde_vs_std.png", list(STDS_HU), by_sd, "image standard deviation σ [HU]",
         "cube phantom, n = 5 (paper Fig. 12)")
    n_maps = (len(SIZES) + len(STDS_HU)) * args.seeds * len(SOLVERS)
    print(f"\n{n_maps} mappings in {elapsed:.1f} s; figures in {out}/")


if __name__ == "__main__":
    main()
