"""Splitting along the ray finds its copies' sites in one walk of the ray
(:func:`tetdose.transport.history._split.ray_sites`); the reference is the exact flight of each
copy from the site before it by the optical depth between them (τ_i − τ_{i−1},
:func:`tetdose.transport.history._photon.flight`), the stream drawn the same way. Rays in every
direction through linear-density tets in vacuum, a notched mesh inside voxels (the walk leaves
and re-enters the mesh and the grid) and a voxel-only grid: the same sites, cells and escapes."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numba import njit
from test_woodcock import MATERIALS, _slab_ct, _slab_mesh

from tetdose._random import next_uniform, seed_for
from tetdose.transport import PhotonSource, Plan, TransportSettings, World
from tetdose.transport.geometry._world import WorldGeometry, start_cell
from tetdose.transport.history._electron import N_COUNTS_DOSE, N_LEDGER_DOSE
from tetdose.transport.history._photon import INTERACTS, flight
from tetdose.transport.history._split import SITE_COLUMNS, ray_sites
from tetdose.transport.run.job import build_job, cross_sections

N_COPIES = 16


@njit(cache=True)
def _sites_both_ways(wg, xs, e, p, d, n, seed):
    """(sites of ray_sites, sites of a flight per copy, both drew the same numbers) for a ray
    from p along d."""
    tally = np.zeros(1)
    counts = np.zeros(N_COUNTS_DOSE, dtype=np.int64)
    ledger = np.zeros(N_LEDGER_DOSE)
    cell, x, y, z, _ = start_cell(wg, p[0], p[1], p[2], d[0], d[1], d[2])
    one_walk = np.full((n, SITE_COLUMNS), np.nan)
    per_copy = np.full((n, SITE_COLUMNS), np.nan)
    if cell < 0:  # the ray misses the world
        return one_walk[:0], per_copy[:0], True
    state = seed_for(seed, 0, 0)
    state_end, found = ray_sites(wg, xs, e, cell, x, y, z, d[0], d[1], d[2], state, n, -1.0,
                                 one_walk, tally, ledger, counts)
    tau_prev, k = 0.0, 0
    state, xi = next_uniform(state)  # one ξ for all the copies: systematic sampling
    for i in range(n):
        tau = -math.log1p(-(i + xi) / n)
        if k < i:  # an earlier copy left the world: so do the rest
            continue
        out, cell, x, y, z = flight(wg, xs, e, cell, x, y, z, d[0], d[1], d[2], tau - tau_prev,
                                    False, tally, counts)
        if out != INTERACTS:
            continue
        per_copy[k, 0], per_copy[k, 1], per_copy[k, 2], per_copy[k, 3] = x, y, z, cell
        tau_prev, k = tau, k + 1
    same_stream = next_uniform(state)[1] == next_uniform(state_end)[1]  # the same numbers drawn
    return one_walk[:found], per_copy[:k], same_stream


def _compare(world: World, e_mev: float, starts: np.ndarray, dirs: np.ndarray) -> int:
    """Every ray: the same sites (to 1e-9 mm) in the same cells; returns the sites compared."""
    plan = Plan((PhotonSource("pencil", (0.0, 0.0, 0.0), (0.0, 0.0, 1.0),
                              energies_mev=[e_mev]),), materials=MATERIALS)
    settings = TransportSettings(10, 2)
    job, _ = build_job(world, plan, settings)
    xs = cross_sections(job, settings)
    wg = WorldGeometry(*job.geom)
    if world.grid is not None:  # the kernels work in the grid's frame
        starts = world.grid.to_grid_frame(starts)
        dirs = dirs @ world.grid.direction
    compared = 0
    for r, (p, d) in enumerate(zip(starts, dirs, strict=True)):
        one, ref, same_stream = _sites_both_ways(wg, xs, e_mev, p, d / np.linalg.norm(d),
                                                 N_COPIES, r)
        assert same_stream
        assert len(one) == len(ref), (r, len(one), len(ref))
        np.testing.assert_array_equal(one[:, 3], ref[:, 3])
        np.testing.assert_allclose(one[:, :3], ref[:, :3], rtol=0, atol=1e-9)
        compared += len(one)
    return compared


def _rays(lo, hi, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """n rays from points drawn in the box [lo, hi] (mm) in isotropic directions."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    return rng.uniform(lo, hi, size=(n, 3)), d / np.linalg.norm(d, axis=1)[:, None]


@pytest.mark.parametrize("e_mev", [0.1, 2.0])
def test_one_walk_finds_the_sites_of_a_flight_per_copy_in_linear_density_tets(e_mev):
    starts, dirs = _rays((-35, -35, -5), (35, 35, 85), 60, 1)
    assert _compare(World(mesh=_slab_mesh()), e_mev, starts, dirs) > 50


@pytest.mark.parametrize("e_mev", [0.1, 2.0])
def test_one_walk_finds_the_sites_of_a_flight_per_copy_in_a_notched_mesh_inside_voxels(e_mev):
    grid, ct = _slab_ct()
    starts, dirs = _rays((-45, -45, -15), (45, 45, 95), 60, 2)
    world = World(mesh=_slab_mesh(notch=True), density=ct)
    assert _compare(world, e_mev, starts, dirs) > 50


def test_one_walk_finds_the_sites_of_a_flight_per_copy_in_voxels():
    _, ct = _slab_ct()
    starts, dirs = _rays((-45, -45, -15), (45, 45, 95), 60, 3)
    assert _compare(World(density=ct), 0.5, starts, dirs) > 50
