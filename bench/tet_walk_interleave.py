"""Do two rays walked in step hide each other's cache misses? (issue 30: why tets trail voxels)

:mod:`tet_crossing_cost` found the tets' photon walks memory-bound on the XVMC case's 216 k-tet
cube: each crossing is a load of the next tet's records that depends on this tet's exit face.
An out-of-order CPU can overlap the misses of independent chains, so walking two rays in one
loop, a crossing of each in turn, would take up to half the time per crossing if the latency
is what costs. Measured here with the walk's own exit-face and link kernels
(:func:`~tetdose.transport.geometry._tet.exit_face`, :func:`~tetdose.transport.geometry._tet.next_tet`:
planes 64 B and link 16 B a tet, no physics) on 2·10⁵ rays from random points in random
directions, on the cube as 8 k tets (0.6 MB of planes and links: cached) and 216 k tets (17 MB),
one ray at a time and two interleaved; best of three per case, 1 thread. Run::

    NUMBA_CACHE_DIR=.numba-cache .venv/bin/python bench/tet_walk_interleave.py

Measured at stop 42 (bench/README), seven runs: 22–32 ns per crossing cached (two rays in step
31–46 ns: the extra bookkeeping); on the 216 k tets 92–201 ns for one ray and 92–147 ns for two,
within a run 0–10 % faster in six runs of seven (37 % once, against an outlying single-ray
figure). The misses hardly overlap, so walking split rays in pairs (or a ray as two halves) would
save at most a few per cent of a tet history, whose walk is a third of it.
"""

from __future__ import annotations

import time
from typing import NamedTuple

import numpy as np
from bench_precision import cube_mesh
from numba import njit

from tetdose.core.transfer import locate_points
from tetdose.transport.geometry._tet import exit_face, next_tet
from tetdose.transport.geometry.tets import mesh_geometry, morton_order

RAYS = 200_000


class Walk(NamedTuple):
    """What a bare walk reads of a tet: its face planes and links."""

    planes: np.ndarray
    link: np.ndarray


@njit(inline="always")
def _cross(g, k, e, x, y, z, u, v, w):
    """(next tet or −1, its entry face, exit point, length [mm]) of one crossing."""
    f, t = exit_face(g, k, x, y, z, u, v, w, e)
    if f < 0 or g.link[k, f] < 0:
        return -1, e, x, y, z, 0.0
    k2, e2 = next_tet(g, k, f)
    return k2, e2, x + t * u, y + t * v, z + t * w, t


@njit
def walk(g, start, p, d, pair):
    """(crossings, total length [mm]) of every ray, one at a time or two in step (``pair``)."""
    crossings, total = 0, 0.0
    step = 2 if pair else 1
    for r in range(0, start.shape[0] - 1, step):
        ka, ea, xa, ya, za = start[r], -1, p[r, 0], p[r, 1], p[r, 2]
        kb = start[r + 1] if pair else -1
        eb, xb, yb, zb = -1, p[r + 1, 0], p[r + 1, 1], p[r + 1, 2]
        while ka >= 0 or kb >= 0:
            if ka >= 0:
                ka, ea, xa, ya, za, t = _cross(g, ka, ea, xa, ya, za, d[r, 0], d[r, 1], d[r, 2])
                total += t
                crossings += ka >= 0
            if kb >= 0:
                kb, eb, xb, yb, zb, t = _cross(g, kb, eb, xb, yb, zb, d[r + 1, 0], d[r + 1, 1],
                                               d[r + 1, 2])
                total += t
                crossings += kb >= 0
    return crossings, total


def main() -> None:
    rng = np.random.default_rng(1)
    p = rng.uniform([-140.0, -140.0, 10.0], [140.0, 140.0, 290.0], (RAYS, 3))
    d = rng.normal(size=(RAYS, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    for cubes in (11, 33):
        mesh = cube_mesh(cubes)
        order = morton_order(mesh.centroids_mm)
        g = mesh_geometry(mesh, np.ones(mesh.n_points), np.zeros(mesh.n_tets, np.int32), order)
        kernel_tet = np.empty_like(order)
        kernel_tet[order] = np.arange(len(order))  # mesh tet → its index in the kernel's order
        tet = locate_points(mesh, p)[0]
        start = np.where(tet >= 0, kernel_tet[tet], -1)
        bare = Walk(g.planes, g.link)
        mb = (g.planes.nbytes + g.link.nbytes) / 1e6
        for pair in (False, True):
            walk(bare, start[:10], p[:10], d[:10], pair)
            best = np.inf
            for _ in range(3):
                t0 = time.perf_counter()
                n, _ = walk(bare, start, p, d, pair)
                best = min(best, (time.perf_counter() - t0) / n * 1e9)
            print(f"{mesh.n_tets:7d} tets ({mb:4.1f} MB), {'two rays in step' if pair else 'one ray':16s}"
                  f": {best:6.1f} ns per crossing ({n / RAYS:.0f} crossings per ray)", flush=True)


if __name__ == "__main__":
    main()
