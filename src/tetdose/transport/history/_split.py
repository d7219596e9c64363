"""njit XVMC's photon splitting along the ray (``splitting_scheme="repeat"``).

**Method** (Kawrakow & Fippel, PMB 45:2163, 2000, sec. 2.3; Fippel, Med. Phys. 26:1466, 1999):
a photon of weight 1 is split into n copies of weight w = 1/n that all leave along its straight
ray. Copy i interacts at the optical depth

    τ_i = −ln(1 − (i + ξ_i)/n),   ξ_i uniform in [0, 1), i = 0 … n − 1,

a stratified sample of the analog free path: each stratum [i/n, (i+1)/n) of the cumulative
probability 1 − e^(−τ) holds one copy, so Σ_i w·g(τ_i) is an unbiased estimate of E[g(τ)] for
any tally g. The τ_i increase with i, so one walk of the ray (the exact flight of
:func:`tetdose.transport.history._photon.flight`, linear density in tets, voxels, hybrid) finds
every site: from site i − 1 it moves on by τ_i − τ_{i−1}. The copies still ahead when the ray
leaves the world escape (ledger: (n − i)·w·E).

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

from tetdose._jit import kernel
from tetdose._random import next_uniform, seed_for
from tetdose.transport.geometry._world import cell_material
from tetdose.transport.history._electron import L_ROULETTE, PHOTON, push_weighted
from tetdose.transport.history._interaction import (
    INCOHERENT,
    REPEAT,
    interaction_products,
    release_products,
)
from tetdose.transport.history._photon import (
    C_LOST,
    ESCAPES,
    INTERACTS,
    L_ESCAPED,
    L_LOST,
    flight,
)

#: Columns of a site row: x, y, z [mm], global cell.
SITE_COLUMNS = 4
_TWO_53 = 9007199254740992.0


@kernel
def ray_sites(wg, xs, e, cell, x, y, z, u, v, w, state, n, sites, tally, ledger, counts):
    """Walk the ray once and write the interaction sites of the n copies (module docstring) to
    ``sites``; book the copies that leave the world: (state, sites found)."""
    wt = 1.0 / n
    tau_prev = 0.0
    for i in range(n):
        state, xi = next_uniform(state)
        tau = -math.log1p(-(i + xi) * wt)
        out, cell2, x, y, z = flight(wg, xs, e, cell, x, y, z, u, v, w, tau - tau_prev, False,
                                     tally, counts)
        if out != INTERACTS:
            if out == ESCAPES:
                ledger[L_ESCAPED] += (n - i) * wt * e
            else:
                ledger[L_LOST] += (n - i) * wt * e
                counts[C_LOST] += 1
            return state, i
        cell, tau_prev = cell2, tau
        sites[i, 0], sites[i, 1], sites[i, 2], sites[i, 3] = x, y, z, cell
    return state, n


@kernel
def split_photon(wg, xs, e, cell, x, y, z, u, v, w, state, n, e_cut, sites, tally, ledger,
                 counts, stack, n_stack):
    """Split a photon of weight 1 into ``n`` copies along its ray, interact each at its site
    with the copies' shared stream, keep one scattered photon (module docstring): (state,
    n_stack)."""
    wt = 1.0 / n
    state, xk = next_uniform(state)
    kin = seed_for(int(xk * _TWO_53), 1, 0)
    state, n_in = ray_sites(wg, xs, e, cell, x, y, z, u, v, w, state, n, sites, tally, ledger,
                            counts)
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
                xs, m, e, u, v, w, kin)
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
