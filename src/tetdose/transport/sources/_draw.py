"""njit loop drawing the source particles of a range of histories, exactly as the transport does.

History h draws its source particle first from its own stream ``seed_for(seed, stream, h)``
(:mod:`tetdose._random`) with :func:`~._sample.sample_source`, which is what
:func:`tetdose.transport.run._batches.run_world` does before transporting it: the particles are
those tetdose's own engine would start, bit for bit, so another engine fed with them (a
phase-space file for ompmc, :mod:`tetdose.coupling.ompmc`) sees the same source. ``qmc``: the
histories' quasi-random points (:mod:`.quasi`; shape (1, 0): none).
"""

from numba import njit

from tetdose._random import seed_for
from tetdose.transport.sources._sample import sample_source


@njit(cache=True)
def draw_particles(src, seed, stream, first, qmc, energy, position, direction):
    """Fill ``energy[i]`` [MeV], ``position[i]`` and ``direction[i]`` with the source particle
    of history ``first + i`` (arrays of equal length, positions in the source arrays' frame)."""
    for i in range(energy.shape[0]):
        state = seed_for(seed, stream, first + i)
        state, e, x, y, z, u, v, w = sample_source(src, state, qmc[i if qmc.shape[1] > 0 else 0])
        energy[i] = e
        position[i, 0], position[i, 1], position[i, 2] = x, y, z
        direction[i, 0], direction[i, 1], direction[i, 2] = u, v, w
