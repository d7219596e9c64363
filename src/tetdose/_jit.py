"""``@kernel`` = ``njit(cache=True, _nrt=False)``: the decorator of small, hot njit helpers.

numba's runtime (NRT) counts references to every array a compiled function holds: an atomic add
on entry and an atomic subtract on exit per array, and a geometry NamedTuple carries thirteen.
Called once per flight, interaction and source photon, that bookkeeping cost more than the
physics: 2.6 µs of a 4.3 µs history on a 48-tet box, and the shared counters bounce between the
cores of a multi-threaded run. Kernels compiled without NRT borrow their arguments without
counting; they must not allocate arrays (numba refuses to compile one that does), so the loops
that allocate (e.g. the batch loops of :mod:`tetdose.transport.run._batches`) keep NRT and call these.
"""

from numba import njit

kernel = njit(cache=True, _nrt=False)
