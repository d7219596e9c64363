"""njit(parallel) batch loops: source sampling and histories, one prange iteration per batch.

Batch b runs histories ``[b·N // B, (b+1)·N // B)`` and writes only row b of the tally, ledger
and counter arrays (no shared ``+=``, numba #7133). History h draws every random number from its
own stream ``seed_for(seed, stream, h)`` (:mod:`tetdose._random`), so the dose is bitwise the same
whatever the thread count or the order batches run in.

The batch loops hold the GIL (no ``nogil``): each call already spreads its batches over every
numba thread, and two calls running at once from Python threads (a multi-threaded dask worker)
would only oversubscribe the cores — and abort under numba's ``workqueue`` threading layer, which
is not thread-safe. The per-photon kernels they call are compiled without NRT
(:mod:`tetdose._jit`).

Source sampling lives in :mod:`tetdose.transport._source`.
"""

import numpy as np
from numba import njit, prange

from tetdose._random import seed_for
from tetdose.transport._geometry_tet import enter_mesh
from tetdose.transport._geometry_voxel import enter_grid
from tetdose.transport._history import (
    C_RELOCATIONS,
    L_ESCAPED,
    L_SOURCE,
    N_COUNTS,
    N_LEDGER,
    history_mesh,
    history_voxel,
)
from tetdose.transport._source import sample_source

#: Secondary photon stack depth (pair production adds one; annihilation photons cannot pair).
STACK_DEPTH = 8


@njit(cache=True, parallel=True)
def run_mesh(g, xs, src, seed, stream, n_hist, n_batches, b_start, b_stop, cutoff,
             track, energy, ledger, counts):
    """Run batches ``b_start … b_stop−1`` on the mesh; batch b fills row ``b − b_start`` of
    energy/ledger/counts (arrays of ``b_stop − b_start`` rows).

    Ledger and counters accumulate in arrays private to the iteration and are copied to their
    row at the end: adjacent rows share cache lines, so per-event writes into them from two
    threads would false-share.
    """
    for b in prange(b_start, b_stop):
        stack = np.empty((STACK_DEPTH, 8))
        led = np.zeros(N_LEDGER)
        cnt = np.zeros(N_COUNTS, dtype=np.int64)
        tally = energy[b - b_start]
        for h in range(b * n_hist // n_batches, (b + 1) * n_hist // n_batches):
            state = seed_for(seed, stream, h)
            state, e, x, y, z, u, v, w = sample_source(src, state)
            led[L_SOURCE] += e
            k, x, y, z, n_reloc = enter_mesh(g, x, y, z, u, v, w)
            cnt[C_RELOCATIONS] += n_reloc
            if k < 0:
                led[L_ESCAPED] += e
                continue
            history_mesh(g, xs, e, k, x, y, z, u, v, w, state, cutoff, track, tally,
                         led, cnt, stack)
        ledger[b - b_start, :] = led
        counts[b - b_start, :] = cnt


@njit(cache=True, parallel=True)
def run_voxel(g, xs, src, seed, stream, n_hist, n_batches, b_start, b_stop, cutoff,
              track, energy, ledger, counts):
    """Voxel twin of :func:`run_mesh`; ``src`` is given in the grid frame."""
    for b in prange(b_start, b_stop):
        stack = np.empty((STACK_DEPTH, 8))
        led = np.zeros(N_LEDGER)
        cnt = np.zeros(N_COUNTS, dtype=np.int64)
        tally = energy[b - b_start]
        for h in range(b * n_hist // n_batches, (b + 1) * n_hist // n_batches):
            state = seed_for(seed, stream, h)
            state, e, x, y, z, u, v, w = sample_source(src, state)
            led[L_SOURCE] += e
            inside, x, y, z = enter_grid(g, x, y, z, u, v, w)
            if not inside:
                led[L_ESCAPED] += e
                continue
            history_voxel(g, xs, e, x, y, z, u, v, w, state, cutoff, track, tally,
                          led, cnt, stack)
        ledger[b - b_start, :] = led
        counts[b - b_start, :] = cnt
