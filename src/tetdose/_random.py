"""Counter-based random numbers for kernels: SplitMix64 hashing of (seed, stream, index).

Each Monte Carlo sample draws from its own stream ``seed_for(master_seed, stream, index)``, so
results do not depend on thread count or on how work is split into batches (the property OpenMC
gets by LCG skip-ahead and MC/DC by ``split_seed``). The generator state is one uint64 held in a
local variable: ``state, u = next_uniform(state)``.

Reference: G. Steele, D. Lea, C. Flood, "Fast splittable pseudorandom number generators",
OOPSLA 2014 (SplitMix64 constants).
"""

import numpy as np
from numba import njit

_GAMMA = np.uint64(0x9E3779B97F4A7C15)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_S30 = np.uint64(30)
_S27 = np.uint64(27)
_S31 = np.uint64(31)
_S11 = np.uint64(11)
_TWO_M53 = 1.0 / 9007199254740992.0


@njit(cache=True, inline="always")
def _mix(z):
    z = (z ^ (z >> _S30)) * _M1
    z = (z ^ (z >> _S27)) * _M2
    return z ^ (z >> _S31)


@njit(cache=True)
def seed_for(master_seed, stream, index):
    """64-bit state of sample ``index`` in ``stream`` under ``master_seed`` (all non-negative ints)."""
    z = _mix(np.uint64(master_seed) + _GAMMA)
    z = _mix(z ^ (np.uint64(stream) * _M2 + _GAMMA))
    return _mix(z ^ (np.uint64(index) * _M1 + _GAMMA))


@njit(cache=True, inline="always")
def next_uniform(state):
    """Advance ``state``; return (new_state, u) with u uniform in [0, 1) (53 random bits)."""
    state = np.uint64(state) + _GAMMA
    return state, float(_mix(state) >> _S11) * _TWO_M53


@njit(cache=True, inline="always")
def next_uniform_or(state, fixed):
    """(state, ξ): the stream's next uniform, or ``fixed`` in its place when ``fixed`` ≥ 0 (a
    quasi-random coordinate); the stream advances either way."""
    state, xi = next_uniform(state)
    return state, fixed if fixed >= 0.0 else xi
