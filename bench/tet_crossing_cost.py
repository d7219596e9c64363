"""What a tet crossing costs in the XVMC case, by mesh size: why tets trail the voxels (issue 30).

The photon transport of :mod:`bench_precision`'s case alone (its settings: 64 / 32 copies along
the ray, history repetition, quasi-random primaries; electron cut-off 19 MeV, so that every
electron deposits where it is set in motion and nothing but the photons walks), on the water cube
as 6·n³ Kuhn tets for n = 11, 22, 33 (8 k, 64 k, 216 k tets; 33 is the case's mesh, a voxel's
mass per tet) and on the 5 mm voxels. Per history it prints the transport CPU (the run's own
``extra["cpu_s"]``: no world build, no pilot), the tet crossings or voxel steps, and the marginal
cost of a crossing between consecutive sizes, (ΔCPU)/(Δcrossings). Run::

    NUMBA_CACHE_DIR=.numba-cache .venv/bin/python bench/tet_crossing_cost.py [HISTORIES] [ROUNDS]

The photons' walks go cell to cell along their rays, each crossing a dependent load of the next
tet's records (planes 64 B, density 32 B, link 16 B, material 4 B: 116 B a tet, 25 MB for the
216 k tets, against 2.6 MB for the voxels' density and material). Measured at stop 41 (best of
five, bench/README): where the walk's records stay in the caches (8 k → 64 k tets) a further
crossing cost 44 ns, about a voxel step; from 64 k to 216 k tets, 145 ns: the scattered photons'
rays leave the field and walk records that no recent history has brought into the cache. The
VM's L3 is shared with its neighbours, so single runs vary (others gave 49 / 118 and 87 / 86 ns):
take the best of several rounds.
"""

from __future__ import annotations

import sys

import numba
import numpy as np
from bench_precision import cube_mesh, parse_settings, plan, settings, water_cube

from tetdose.transport import simulate
from tetdose.transport.history.result import COUNT_KEYS

SIZES = (11, 22, 33)
CASE = ("photon_splitting=64", "secondary_photon_splitting=32", "splitting_scheme='repeat'",
        "quasi_random=True", "max_energy_loss_fraction=0.5", "electron_cutoff_mev=19")


def per_history(world, pl, n: int, rounds: int, extra: dict[str, object]
                ) -> tuple[float, float]:
    """(best transport CPU [µs], crossings or voxel steps) per history over ``rounds`` runs."""
    simulate(world, pl, settings(2000, extra), progress=False)  # compile / load, build caches
    best, steps = np.inf, 0.0
    for _ in range(rounds):
        res = simulate(world, pl, settings(n, extra), progress=False)
        best = min(best, res.extra["cpu_s"] / n * 1e6)
        c = res.counts_per_batch.sum(axis=0)
        steps = (c[COUNT_KEYS.index("tet_crossings")] + c[COUNT_KEYS.index("voxel_steps")]) / n
    return best, steps


def main() -> None:
    n = int(float(sys.argv[1])) if len(sys.argv) > 1 else 40_000
    rounds = int(sys.argv[2]) if len(sys.argv) > 2 else 3
    numba.set_num_threads(1)
    extra = parse_settings(list(CASE))
    pl = plan()
    print(f"XVMC case, photons only (electrons deposited where they start), {n} histories, "
          f"best of {rounds}, 1 thread")
    t_v, s_v = per_history(water_cube(), pl, n, rounds, extra)
    print(f"voxels 60³ (216 000, 2.6 MB)      {s_v:6.1f} steps/history     {t_v:6.1f} µs/history "
          f"({t_v / s_v * 1e3:4.0f} ns per step, all included)", flush=True)
    rows = []
    for cubes in SIZES:
        mesh = cube_mesh(cubes)
        t, s = per_history(mesh, pl, n, rounds, extra)
        rows.append((t, s))
        mb = mesh.n_tets * 116 / 1e6
        line = (f"tets {mesh.n_tets:7d} ({mb:5.1f} MB)       {s:6.1f} crossings/history "
                f"{t:6.1f} µs/history")
        if len(rows) > 1:
            (t0, s0), (t1, s1) = rows[-2], rows[-1]
            line += f"  marginal {(t1 - t0) / (s1 - s0) * 1e3:4.0f} ns per crossing"
        print(line, flush=True)


if __name__ == "__main__":
    main()
