"""njit(parallel) batch loop: source sampling and histories, one prange iteration per batch.

Batch b runs histories ``[b·N // B, (b+1)·N // B)`` and writes only row b of the tally, ledger
and counter arrays (no shared ``+=``, numba #7133). A call runs the part ``[o_from, o_to)`` of
every batch (offsets from the batch's first history): a batch may be run in several calls, each
continuing the sums of its row where the last left them, in history order — the same float
operations in the same order as one call, so bitwise the same rows — and the caller gets control
(Ctrl-C, SIGTERM, progress) between calls (:func:`tetdose.transport.run.job.run_batches`).
History h draws every random number from its own stream ``seed_for(seed, stream, h)``
(:mod:`tetdose._random`), so the dose is bitwise the same whatever the thread count or the
order batches run in.

The batch loop holds the GIL (no ``nogil``): each call already spreads its batches over every
numba thread, and two calls running at once from Python threads (a multi-threaded dask worker)
would only oversubscribe the cores — and abort under numba's ``workqueue`` threading layer, which
is not thread-safe. The per-photon kernels it calls are compiled without NRT
(:mod:`tetdose._jit`).

Source sampling lives in :mod:`tetdose.transport.sources._sample`.
"""

import numpy as np
from numba import njit, prange

from tetdose._random import seed_for
from tetdose.transport.geometry._world import WorldGeometry, start_cell
from tetdose.transport.history._photon import (
    C_MISSED,
    C_RELOCATIONS,
    L_ESCAPED,
    L_SOURCE,
    history,
)
from tetdose.transport.sources._sample import sample_source

#: Secondary photon stack depth (pair production adds one; annihilation photons cannot pair).
STACK_DEPTH = 8


@njit(cache=True, parallel=True)
def run_world(tet, vox, tri_lo, tri_n, tri_start, tri_items, xs, src, seed, stream, n_hist,
              n_batches, b_start, b_stop, o_from, o_to, qmc, cutoff, track, energy, ledger,
              counts):
    """Run histories ``o_from … o_to−1`` (offsets within each batch, see module doc) of batches
    ``b_start … b_stop−1`` in the world of the fields of a
    :class:`~._geometry_world.WorldGeometry`; batch b adds to row ``b − b_start`` of
    energy/ledger/counts (arrays of ``b_stop − b_start`` rows; sources in the world's frame).
    ``qmc``: quasi-random points of the histories from batch ``b_start``'s first on
    (:mod:`tetdose.transport.sources.quasi`; shape (1, 0): pseudo-random sources).

    The world comes in field by field and is rebuilt inside the loop body: numba's parallel
    loops cannot take a tuple that nests tuples of arrays as an argument.

    Ledger and counters accumulate in arrays private to the iteration and are copied to their
    row at the end: adjacent rows share cache lines, so per-event writes into them from two
    threads would false-share.
    """
    for b in prange(b_start, b_stop):
        wg = WorldGeometry(tet, vox, tri_lo, tri_n, tri_start, tri_items)
        stack = np.empty((STACK_DEPTH, 8))
        led = ledger[b - b_start].copy()
        cnt = counts[b - b_start].copy()
        tally = energy[b - b_start]
        first, end = b * n_hist // n_batches, (b + 1) * n_hist // n_batches
        for h in range(min(first + o_from, end), min(first + o_to, end)):
            state = seed_for(seed, stream, h)
            q = qmc[h - b_start * n_hist // n_batches if qmc.shape[1] > 0 else 0]
            state, e, x, y, z, u, v, w = sample_source(src, state, q)
            led[L_SOURCE] += e
            cell, x, y, z, n_reloc = start_cell(wg, x, y, z, u, v, w)
            cnt[C_RELOCATIONS] += n_reloc
            if cell < 0:
                led[L_ESCAPED] += e
                cnt[C_MISSED] += 1
                continue
            history(wg, xs, e, cell, x, y, z, u, v, w, state, cutoff, track, tally, led, cnt,
                    stack)
        ledger[b - b_start, :] = led
        counts[b - b_start, :] = cnt
