"""njit XVMC's photon splitting along the ray (``splitting_scheme="repeat"``).

**Method** (Kawrakow & Fippel, PMB 45:2163, 2000, sec. 2.3; Fippel, Med. Phys. 26:1466, 1999):
a photon of weight 1 is split into n copies of weight w = 1/n that all leave along its straight
ray. Copy i interacts at the optical depth

    τ_i = −ln(1 − (i + ξ)/n),   one ξ uniform in [0, 1) for all copies, i = 0 … n − 1,

(with quasi-random primaries the source photon's ξ is a coordinate of the history's Sobol point)

a systematic sample of the analog free path: the cumulative probabilities 1 − e^(−τ_i) lie 1/n
apart, one in each stratum [i/n, (i+1)/n), each on its own uniform in its stratum, so
Σ_i w·g(τ_i) is an unbiased estimate of E[g(τ)] for any tally g (the copies are dependent, the
expectation is a sum over them). Evenly spaced sites put a nearly fixed number of copies in a
cell the ray crosses; with one ξ_i per stratum (stratified sampling, the earlier scheme) adjacent
copies could bunch or leave a gap. XVMC case (64 / 32 copies, quasi-random, ESTEPE 0.5, the
same histories and cost): median σ 3.42 → 3.11 %, σ² ÷ 1.21 (three streams: ÷ 1.19–1.22).
The τ_i increase with i, so one walk of the ray finds every site: it adds up the optical depth
cell by cell (voxels: μ ρ per mm; tets: the exact column of the linear density, as
:func:`tetdose.transport.history._photon.flight`) and drops copy i where the sum passes τ_i; at
the mesh's boundary the exact flight carries it across worlds and vacuum. The copies still
ahead when the ray leaves the world escape (ledger: (n − i)·w·E).

The copies share their interaction's random numbers (one stream ``kin`` per split photon, fresh
for every split photon): at sites of one material they all have the same interaction, the same
scattered photon direction and energy, and set in motion electrons of one energy and direction,
whose one track is sampled once and replayed from every site with weight w
(:mod:`tetdose.transport.history._repeat`). Each copy is, on its own, an analog photon, so the
dose is unbiased; the copies' deposits are correlated, but they lie at different depths, mostly
in different cells.

Of the n scattered photons one is kept with weight 1: that of the site j, j uniform in
0 … n − 1 (none if copy j escaped or was absorbed). Each copy's photon thus survives with
probability w and weight 1: Russian roulette with the survivors made exclusive, which keeps
exactly one photon shower per split photon. Ledger L_ROULETTE: + w·E' for every photon killed,
− (1 − w)·E' for the survivor. The survivor is itself split when it is followed (it is pushed
beneath the sites' electrons, so they replay one track before the next photon records its own).
"""

import math

from numba import njit

from tetdose._constants import MM_PER_CM
from tetdose._jit import kernel
from tetdose._random import next_uniform, next_uniform_or, seed_for
from tetdose.transport.geometry._tet import exit_face, next_tet, prefetch_neighbours
from tetdose.transport.geometry._voxel import dda_init, dda_step
from tetdose.transport.geometry._walk import (
    MAX_SWITCHES,
    after_grid,
    column_distance,
    tet_column,
    voxel_material,
    voxel_stretch_end,
)
from tetdose.transport.geometry._world import HIT_TOL_MM, cell_material, voxel_ijk
from tetdose.transport.history._electron import L_ROULETTE, PHOTON, push_weighted
from tetdose.transport.history._interaction import (
    INCOHERENT,
    REPEAT,
    interaction_products,
    release_products,
)
from tetdose.transport.history._photon import (
    C_CROSSINGS,
    C_LOST,
    C_VOXEL_STEPS,
    ENTERS,
    ESCAPES,
    INTERACTS,
    L_ESCAPED,
    L_LOST,
    LOST,
    flight,
)
from tetdose.transport.physics._photon import transport_coefficients

#: Columns of a site row: x, y, z [mm], global cell.
SITE_COLUMNS = 4
_TWO_53 = 9007199254740992.0


@njit(cache=True, inline="always")
def voxel_sites(wg, xs, e, vid, x, y, z, u, v, w, sites, i, n, acc, counts):
    """Walk the voxels once from (x, y, z) in voxel ``vid``, where the ray's optical depth is
    ``acc``, and write the sites of copies i, i + 1, … whose optical depths (``sites[·, 0]``)
    it reaches (the arithmetic of :func:`~._photon.flight_voxel`): (copies found, outcome,
    cell, x, y, z, optical depth) — INTERACTS once all n are found, else where the walk left
    the grid (ESCAPES) or met the mesh (ENTERS: the tet)."""
    g = wg.vox
    off = wg.tet.planes.shape[0]
    nx, ny = g.n[0], g.n[1]
    ii, jj, kk = voxel_ijk(g, vid)
    sx, sy, sz, tx, ty, tz, dx, dy, dz = dda_init(g, ii, jj, kk, x, y, z, u, v, w)
    t_cur = 0.0
    m_prev = -1
    mu = 0.0
    steps = 0
    while True:
        vid = (kk * ny + jj) * nx + ii
        m, listed = voxel_material(g, vid)
        if m != m_prev:
            mu, _ = transport_coefficients(xs, m, e)
            m_prev = m
        b, t_end = voxel_stretch_end(wg, listed, ii, jj, kk, x, y, z, u, v, w, t_cur,
                                     -HIT_TOL_MM, tx, ty, tz)
        t_end = max(t_end, t_cur)
        rate = mu * g.density[vid] / MM_PER_CM  # optical depth per mm
        tau_end = acc + rate * (t_end - t_cur)
        while i < n and sites[i, 0] < tau_end:
            t = t_cur + (sites[i, 0] - acc) / rate
            sites[i, 0], sites[i, 1], sites[i, 2], sites[i, 3] = (x + t * u, y + t * v,
                                                                  z + t * w, off + vid)
            i += 1
        if i == n:
            counts[C_VOXEL_STEPS] += steps
            return i, INTERACTS, -1, x, y, z, acc
        acc = tau_end
        if b >= 0:
            counts[C_VOXEL_STEPS] += steps
            return i, ENTERS, wg.tet.bnd_tet[b], x + t_end * u, y + t_end * v, z + t_end * w, acc
        t_cur = t_end
        steps += 1
        ii, jj, kk, tx, ty, tz, inside = dda_step(ii, jj, kk, tx, ty, tz, sx, sy, sz, dx, dy, dz,
                                                  g.n)
        if not inside:
            counts[C_VOXEL_STEPS] += steps
            return i, ESCAPES, -1, x + t_cur * u, y + t_cur * v, z + t_cur * w, acc


@njit(cache=True, inline="always")
def mesh_sites(g, xs, e, k, x, y, z, u, v, w, sites, i, n, acc, counts):
    """Walk the tets once from (x, y, z) in tet ``k`` (the arithmetic of
    :func:`~._photon.flight_mesh`: linear density, exact column) and write the sites of copies
    i, i + 1, … it reaches: (copies found, outcome, tet, x, y, z, optical depth) — INTERACTS
    once all n are found, else LOST: the ray leaves the mesh in this tet, or the walk needs a
    relocation, and the caller's exact flight goes on from its entry (x, y, z)."""
    m_prev = -1
    mu = 0.0
    entry = -1
    crossings = 0
    no_tally = g.density[:0, 0]  # the walk writes no tally: nothing of it to prefetch
    while True:
        m = g.material[k]
        if m != m_prev:
            mu, _ = transport_coefficients(xs, m, e)
            m_prev = m
        prefetch_neighbours(g, k, entry, True, no_tally)
        f, t = exit_face(g, k, x, y, z, u, v, w, entry)
        if f < 0 or t <= 0.0 or g.link[k, f] < 0:
            counts[C_CROSSINGS] += crossings
            return i, LOST, k, x, y, z, acc
        rho0, a, col_exit = tet_column(g, k, x, y, z, u, v, w, t)
        tau_end = acc + mu * col_exit / MM_PER_CM
        while i < n and sites[i, 0] < tau_end:
            s = column_distance(rho0, a, (sites[i, 0] - acc) * MM_PER_CM / mu, 0.0)
            sites[i, 0], sites[i, 1], sites[i, 2], sites[i, 3] = (x + s * u, y + s * v,
                                                                  z + s * w, k)
            i += 1
        if i == n:
            counts[C_CROSSINGS] += crossings
            return i, INTERACTS, k, x, y, z, acc
        acc = tau_end
        x, y, z = x + t * u, y + t * v, z + t * w
        k, entry = next_tet(g, k, f)
        crossings += 1


@kernel
def ray_sites(wg, xs, e, cell, x, y, z, u, v, w, state, n, q_shift, sites, tally, ledger, counts):
    """Write the interaction sites of the n copies (module docstring) to ``sites``; book the
    copies that leave the world: (state, sites found). ``q_shift``: the copies' offset ξ from the
    history's quasi-random point, or −1 (drawn from the stream, which advances either way).

    All n optical depths are drawn first (the walk draws nothing: the stream is that of a walk
    per copy). Voxels and tets are walked once for all the copies they hold
    (:func:`voxel_sites`, :func:`mesh_sites`); where the single walk stops in the mesh (its
    boundary, a relocation), the exact flight of :func:`~._photon.flight` takes the next copy
    on, through vacuum and across worlds, and the single walk resumes from its site.
    """
    wt = 1.0 / n
    state, xi = next_uniform_or(state, q_shift)
    for i in range(n):
        sites[i, 0] = -math.log1p(-(i + xi) * wt)
    m_tets = wg.tet.planes.shape[0]
    acc = 0.0  # optical depth of the ray up to (x, y, z)
    i = switches = 0
    while i < n:
        if switches > MAX_SWITCHES:  # worlds handing the ray back and forth without progress
            ledger[L_LOST] += (n - i) * wt * e
            counts[C_LOST] += 1
            break
        switches += 1
        if cell >= m_tets:
            i, out, cell2, x, y, z, acc = voxel_sites(wg, xs, e, cell - m_tets, x, y, z, u, v, w,
                                                      sites, i, n, acc, counts)
        else:
            i, out, cell2, x, y, z, acc = mesh_sites(wg.tet, xs, e, cell, x, y, z, u, v, w,
                                                     sites, i, n, acc, counts)
        if i == n:
            break
        if out == ENTERS:  # from a voxel into the mesh
            cell = cell2
            continue
        if out == ESCAPES:  # left the grid: vacuum, maybe a mesh part beyond
            cell, x, y, z = after_grid(wg, x, y, z, u, v, w)
            if cell < 0:
                ledger[L_ESCAPED] += (n - i) * wt * e
                break
            continue
        tau = sites[i, 0]  # the exact flight of copy i from the tet the single walk stopped in
        out, cell, x, y, z = flight(wg, xs, e, cell2, x, y, z, u, v, w, tau - acc, False, tally,
                                    counts)
        if out != INTERACTS:
            if out == ESCAPES:
                ledger[L_ESCAPED] += (n - i) * wt * e
            else:
                ledger[L_LOST] += (n - i) * wt * e
                counts[C_LOST] += 1
            break
        acc = tau
        sites[i, 0], sites[i, 1], sites[i, 2], sites[i, 3] = x, y, z, cell
        i += 1
    return state, i


@kernel
def split_photon(wg, xs, e, cell, x, y, z, u, v, w, state, n, qs, e_cut, sites, tally,
                 ledger, counts, stack, n_stack):
    """Split a photon of weight 1 into ``n`` copies along its ray, interact each at its site
    with the copies' shared stream, keep one scattered photon (module docstring): (state,
    n_stack). ``qs``: (offset ξ, Compton, azimuth) uniforms of the history's quasi-random point
    for the source photon's split (:mod:`tetdose.transport.sources._sample`), −1 where the
    streams draw them."""
    wt = 1.0 / n
    state, xk = next_uniform(state)
    kin = seed_for(int(xk * _TWO_53), 1, 0)
    state, n_in = ray_sites(wg, xs, e, cell, x, y, z, u, v, w, state, n, qs[0], sites, tally,
                            ledger, counts)
    state, xj = next_uniform(state)
    keep = min(int(xj * n), n - 1)
    slot = n_stack
    if keep < n_in:  # the survivor's row, beneath the electrons the sites push
        n_stack = push_weighted(stack, n_stack, PHOTON, 0.0, x, y, z, u, v, w, cell, 1.0, tally,
                                ledger, counts)
    m_last = -1
    kind, e2, u2, v2, w2, t1, eu, ev, ew, t2, pu, pv, pw = 0, 0.0, u, v, w, 0.0, u, v, w, 0.0, u, v, w
    for i in range(n_in):
        sx, sy, sz, c = sites[i, 0], sites[i, 1], sites[i, 2], int(sites[i, 3])
        m = cell_material(wg, c)
        if m != m_last:  # the shared stream gives the same products in the same material
            _, kind, e2, u2, v2, w2, t1, eu, ev, ew, t2, pu, pv, pw = interaction_products(
                xs, m, e, u, v, w, kin, qs[1], qs[2])
            m_last = m
        state, n_stack = release_products(state, kind, t1, eu, ev, ew, t2, pu, pv, pw, sx, sy,
                                          sz, c, e_cut, wt, REPEAT, tally, ledger, counts, stack,
                                          n_stack)
        if kind != INCOHERENT:
            continue
        if i == keep and slot < n_stack:
            ledger[L_ROULETTE] -= (1.0 - wt) * e2
            push_weighted(stack, slot, PHOTON, e2, sx, sy, sz, u2, v2, w2, c, 1.0, tally, ledger,
                          counts)
        else:
            ledger[L_ROULETTE] += wt * e2
    return state, n_stack
