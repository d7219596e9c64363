"""Mesh-only and voxel-only transport speed of this tree against another checkout (A/B).

Run: ``.venv/bin/python bench/bench_ab.py OTHER_CHECKOUT [HISTORIES] [ROUNDS]``, e.g. the code
before the hybrid world: ``git worktree add ../before 8fae71e`` then
``.venv/bin/python bench/bench_ab.py ../before``. Each round runs both trees in turn (fresh
processes, each with its own numba cache keyed on its sources, 1 thread) on the 48 k-tet water
box and its matched 8 k-voxel grid of ``bench_transport.py`` (1.25 MeV 100 × 100 mm² field);
a run prints the best CPU time per history of 5 repetitions. Printed: per round and tree the
figures, then the best of the rounds and the ratio this / other. Interleaving the rounds spreads
the shared VM's load over both trees.
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parents[1]

_RUN = r"""
import sys, time
import numba, numpy as np
sys.path.insert(0, {bench!r})
from bench_transport import box, PLAN
from tetdose.transport import simulate, TransportSettings
numba.set_num_threads(1)
mesh, img = box(20)
n = {n}
for name, geom in (("mesh", mesh), ("voxel", img)):
    simulate(geom, PLAN, TransportSettings(20, 2, physics="kerma"), progress=False)
    best = np.inf
    for _ in range(5):
        t = time.process_time()
        simulate(geom, PLAN, TransportSettings(n, 10, 1, physics="kerma"), progress=False)
        best = min(best, time.process_time() - t)
    print(name, best / n * 1e6)
"""


def _cache_dir(tree: Path) -> str:
    h = hashlib.sha1()
    for p in sorted((tree / "src" / "tetdose").rglob("*.py")):
        h.update(p.read_bytes())
    return str(tree / ".numba-cache" / f"ab-{h.hexdigest()[:12]}")


def run_tree(tree: Path, n: int) -> dict[str, float]:
    env = {**os.environ, "PYTHONPATH": str(tree / "src"), "NUMBA_CACHE_DIR": _cache_dir(tree)}
    out = subprocess.run([sys.executable, "-c", _RUN.format(bench=str(HERE / "bench"), n=n)],
                         env=env, check=True, capture_output=True, text=True).stdout
    return {line.split()[0]: float(line.split()[1]) for line in out.splitlines() if line}


def main(other: Path, n: int, rounds: int) -> None:
    trees = {"this": HERE, "other": other.resolve()}
    best: dict[tuple[str, str], float] = {}
    for r in range(rounds):
        for name, tree in trees.items():
            figures = run_tree(tree, n)
            for kind, us in figures.items():
                best[name, kind] = min(best.get((name, kind), float("inf")), us)
            print(f"round {r + 1} {name:5s} ({tree}): " + ", ".join(
                f"{k} {v:.3f} µs/history" for k, v in figures.items()), flush=True)
    for kind in ("mesh", "voxel"):
        print(f"{kind}: this {best['this', kind]:.3f} / other {best['other', kind]:.3f} µs per "
              f"history = {best['this', kind] / best['other', kind]:.3f}× (best of {rounds})")


if __name__ == "__main__":
    if len(sys.argv) < 2:
        print("bench_ab: give another checkout to compare with (see the module docstring); "
              "skipped")
        sys.exit(0)
    main(Path(sys.argv[1]), int(float(sys.argv[2])) if len(sys.argv) > 2 else 50_000,
         int(sys.argv[3]) if len(sys.argv) > 3 else 3)
