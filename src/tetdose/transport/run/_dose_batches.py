"""njit(parallel) batch loop of dose mode: coupled photon–electron histories, one prange per batch.

The batch layout, the per-history streams ``seed_for(seed, stream, h)``, the private
per-batch ledgers and the parts ``[o_from, o_to)`` of batches run per call are those of
:mod:`tetdose.transport.run._batches` (bitwise the same dose whatever the thread count and the
split of batches into calls). A source particle comes from one of four groups, chosen with the
cumulative probabilities ``group_cdf``: photon beams, electron beams, positron beams (each a
:class:`~tetdose.transport.sources._sample.SourceArrays`) and volume sources
(:class:`~tetdose.transport.sources._volume.VolumeArrays`, born inside the world's cells).
A source photon is followed as ``n_split`` copies of weight 1/n_split, one after the other on the
history's stream (photon splitting, :mod:`tetdose.transport.history._coupled`; ``follow``: their
electrons are followed with that weight, else rouletted); with ``repeat`` the history splits
every photon of weight 1 itself, along its ray (:mod:`tetdose.transport.history._split`).
"""

import numpy as np
from numba import njit, prange

from tetdose._random import next_uniform, seed_for
from tetdose.transport.geometry._world import WorldGeometry, start_cell
from tetdose.transport.history._coupled import coupled_history
from tetdose.transport.history._electron import (
    ELECTRON,
    ELECTRON_MASS_MEV,
    PHOTON,
    POSITRON,
    STACK_COLUMNS,
    WaterTally,
)
from tetdose.transport.history._photon import C_MISSED, C_RELOCATIONS, L_ESCAPED, L_SOURCE
from tetdose.transport.history._repeat import KEY_SIZE, TRACK_COLUMNS, TRACK_ROWS
from tetdose.transport.history._split import SITE_COLUMNS
from tetdose.transport.sources._sample import Q_AZIMUTH, Q_COMPTON, Q_SPLIT, sample_source
from tetdose.transport.sources._volume import sample_volume

#: Stack depth for mixed particles (a shower waits depth-first: photons, δ-rays, brems,
#: annihilation photons; a photon split along its ray adds up to 2 per copy and its survivor,
#: and a photon split while another waits: 4 per copy),
#: and the buffer of cells one electron step may cross.
STACK_DEPTH = 64
STEP_CELLS = 256


@njit(cache=True, inline="always")
def _sample_group(wg, src_g, src_e, src_p, vol, group_cdf, state, q):
    """(state, species, energy, cell, x, y, z, u, v, w, relocations) of one source particle;
    cell −1 if a beam particle misses the world."""
    state, xi = next_uniform(state)
    group = 0
    while group < 3 and group_cdf[group] <= xi:
        group += 1
    if group == 3:
        state, sp, e, cell, x, y, z, u, v, w = sample_volume(wg, vol, state)
        return state, sp, e, cell, x, y, z, u, v, w, 0
    if group == 0:
        sp = PHOTON
        state, e, x, y, z, u, v, w = sample_source(src_g, state, q)
    elif group == 1:
        sp = ELECTRON
        state, e, x, y, z, u, v, w = sample_source(src_e, state, q)
    else:
        sp = POSITRON
        state, e, x, y, z, u, v, w = sample_source(src_p, state, q)
    cell, x, y, z, n_reloc = start_cell(wg, x, y, z, u, v, w)
    return state, sp, e, cell, x, y, z, u, v, w, n_reloc


@njit(cache=True, parallel=True)
def run_world_dose(tet, vox, tri_lo, tri_n, tri_start, tri_items, xs, ln_mu_hat, et, sig_hat,
                   src_g, src_e, src_p, vol, group_cdf, seed, stream, n_hist, n_batches, b_start,
                   b_stop, o_from, o_to, qmc, photon_cutoff, f_loss, n_split, n_split2, scheme,
                   rr_mev, energy, ledger, counts, l_water, water):
    """Run histories ``o_from … o_to−1`` of batches ``b_start … b_stop−1`` (as
    :func:`~._batches.run_world`): batch b adds to row
    ``b − b_start`` of energy [MeV per cell], ledger (:data:`N_LEDGER_DOSE` columns) and counts
    (:data:`N_COUNTS_DOSE`). ``ln_mu_hat`` the photons' majorant table for Woodcock tracking
    through the mesh (empty: they walk it), ``et`` electron tables, ``sig_hat`` their
    hard-event majorant,
    ``photon_cutoff`` [MeV], ``f_loss`` the largest energy-loss fraction per electron step,
    ``n_split`` the copies of each source photon (1: no splitting; ``n_split2`` ≤ n_split those
    of a later photon of weight 1 with ``scheme`` 2), ``scheme`` what becomes of
    their electrons (0 roulette, 1 followed with weight 1/n_split, 2 one track replayed for
    every copy, :mod:`tetdose.transport.history._repeat`), ``rr_mev`` the range
    rejection's largest electron energy [MeV] (0: off), ``qmc`` the quasi-random source points
    (as :func:`~._batches.run_world`); ``l_water`` (2, n_e) water's L/ρ on the grid of ``et``
    and ``water`` (rows, 2, n_cells) the dose-to-water sums A, B of each batch row (n_cells 0:
    not tallied; :class:`~tetdose.transport.history._electron.WaterTally`).
    """
    for b in prange(b_start, b_stop):
        wg = WorldGeometry(tet, vox, tri_lo, tri_n, tri_start, tri_items)
        stack = np.empty((STACK_DEPTH + 4 * n_split, STACK_COLUMNS))
        sites = np.empty((n_split, SITE_COLUMNS))
        bcell = np.empty(STEP_CELLS, dtype=np.intp)
        bcol = np.empty(STEP_CELLS)
        trk = np.empty((TRACK_ROWS, TRACK_COLUMNS))
        key = np.zeros(KEY_SIZE)
        led = ledger[b - b_start].copy()
        cnt = counts[b - b_start].copy()
        tally = energy[b - b_start]
        dw = WaterTally(l_water, water[b - b_start, 0], water[b - b_start, 1])
        first, end = b * n_hist // n_batches, (b + 1) * n_hist // n_batches
        for h in range(min(first + o_from, end), min(first + o_to, end)):
            state = seed_for(seed, stream, h)
            q = qmc[h - b_start * n_hist // n_batches if qmc.shape[1] > 0 else 0]
            state, sp, e, cell, x, y, z, u, v, w, n_reloc = _sample_group(
                wg, src_g, src_e, src_p, vol, group_cdf, state, q)
            e_ledger = e + (2.0 * ELECTRON_MASS_MEV if sp == POSITRON else 0.0)
            led[L_SOURCE] += e_ledger
            cnt[C_RELOCATIONS] += n_reloc
            if cell < 0:
                led[L_ESCAPED] += e_ledger
                cnt[C_MISSED] += 1
                continue
            sch = scheme if n_split > 1 else min(scheme, 1)
            copies = n_split if sp == PHOTON and sch < 2 else 1  # "repeat" splits in the history
            wt = 1.0 / copies
            key[0] = -1.0  # no track of another history is replayed
            qs = ((q[Q_SPLIT], q[Q_COMPTON], q[Q_AZIMUTH]) if q.shape[0] > Q_AZIMUTH
                  else (-1.0, -1.0, -1.0))
            for _ in range(copies):
                state = coupled_history(wg, xs, ln_mu_hat, et, sig_hat, sp, e, cell, x, y, z,
                                        u, v, w, state, photon_cutoff, f_loss, wt, sch, n_split,
                                        n_split2, rr_mev, qs, tally, led, cnt, stack, bcell,
                                        bcol, sites, trk, key, dw)
        ledger[b - b_start, :] = led
        counts[b - b_start, :] = cnt
