"""njit photon interactions of dose mode: what a photon's interaction sets in motion.

The interaction is chosen from the branching fractions of
:func:`tetdose.transport.physics._photon.interact`, but the charged particles it releases are
transported instead of depositing their energy where they are born
(:mod:`tetdose.transport.physics._photon_electrons` gives their energies and directions):

- incoherent: the photon continues with E' (Klein–Nishina), the recoil electron T = E − E' goes
  along p = E·d − E'·d';
- photoelectric: the photon is absorbed, a photo-electron T = E goes at the Sauter angle;
- pair (E > 2mc²): the photon is absorbed, an electron and a positron share E − 2mc² uniformly,
  each at its leading-term angle, at opposite azimuths.

What becomes of a charged particle released by a photon of statistical weight w < 1 is the
splitting scheme's (:mod:`tetdose.transport.history._coupled`): Russian roulette (survival w,
then weight 1; ``ROULETTE``), followed with weight w (``FOLLOW``), or followed with weight w as
a replayed track (``REPEAT``, :mod:`tetdose.transport.history._repeat`). A charged particle born
below the electron cut-off deposits w × T where it is born (a positron's annihilation photons
get weight w). The roulette's energy balance is the ledger column L_ROULETTE: + w·E for a killed
particle, − (1 − w)·E for a survivor (E = T, + 2mc² for a positron).
"""

import math

from numba import njit

from tetdose._jit import kernel
from tetdose._random import next_uniform, next_uniform_or
from tetdose.transport.history._electron import (
    ELECTRON,
    ELECTRON_MASS_MEV,
    L_E_CUTOFF,
    PHOTON,
    POSITRON,
    REPLAY,
    push,
    push_weighted,
    roulette_survives,
    stop_charged,
)
from tetdose.transport.physics._photon import (
    branching_fractions,
    isotropic_direction,
    klein_nishina_inverse,
    rotate_direction,
    sample_klein_nishina,
)
from tetdose.transport.physics._photon_electrons import (
    compton_electron_direction,
    sample_leading_term_cos,
    sample_sauter_cos,
)

_TWO_PI = 2.0 * math.pi
#: Splitting schemes (settings.SPLITTING_SCHEMES in order): electron roulette, follow, repeat.
ROULETTE, FOLLOW, REPEAT = 0, 1, 2
#: Interaction kinds of :func:`interaction_products`.
INCOHERENT, PAIR, PHOTOELECTRIC = 0, 1, 2


@njit(cache=True, inline="always")
def release(state, sp, t, x, y, z, u, v, w, cell, e_cut, wt, scheme, tally, ledger, counts,
            stack, n_stack):
    """An e± of kinetic energy ``t`` set in motion at (x, y, z) by a photon of weight ``wt``:
    above the cut-off it is pushed with weight wt if ``scheme`` is FOLLOW (XVMC's splitting; an
    electron as REPLAY if REPEAT), else it plays Russian roulette (if wt < 1) and is pushed with
    weight 1 (module docstring); below, wt × t stays there (a positron's annihilation photons get
    weight wt)."""
    if t > e_cut:
        if scheme != ROULETTE:
            sp_push = REPLAY if scheme == REPEAT and sp == ELECTRON else sp
            return state, push_weighted(stack, n_stack, sp_push, t, x, y, z, u, v, w, cell, wt,
                                        tally, ledger, counts)
        if wt < 1.0:
            e_ledger = t + (2.0 * ELECTRON_MASS_MEV if sp == POSITRON else 0.0)
            state, survives = roulette_survives(state, wt, e_ledger, ledger)
            if not survives:
                return state, n_stack
        return state, push(stack, n_stack, sp, t, x, y, z, u, v, w, cell, tally, ledger, counts)
    if wt == 1.0:
        return stop_charged(state, sp, t, x, y, z, cell, 1.0, tally, ledger, counts, stack,
                            n_stack)
    tally[cell] += t * wt
    ledger[L_E_CUTOFF] += t * wt
    if sp == POSITRON:
        state, au, av, aw = isotropic_direction(state)
        n_stack = push_weighted(stack, n_stack, PHOTON, ELECTRON_MASS_MEV, x, y, z, au, av, aw,
                                cell, wt, tally, ledger, counts)
        n_stack = push_weighted(stack, n_stack, PHOTON, ELECTRON_MASS_MEV, x, y, z, -au, -av,
                                -aw, cell, wt, tally, ledger, counts)
    return state, n_stack


@kernel
def interaction_products(xs, m, e, u, v, w, state, q_kn=-1.0, q_phi=-1.0):
    """Sample one interaction of a photon of energy ``e`` [MeV] in material m (module docstring):
    (state, kind, e', u', v', w' of the photon, T₁, direction of the first charged particle,
    T₂, direction of the second). ``kind``: INCOHERENT (the photon goes on; an electron),
    PAIR (an electron, then a positron) or PHOTOELECTRIC (an electron). ``q_kn``, ``q_phi`` ≥ 0:
    the Compton scatter (by inversion, :func:`klein_nishina_inverse`) and its azimuth from these
    uniforms (a quasi-random point's) instead of the stream."""
    p_incoherent, p_pair = branching_fractions(xs, m, e)
    state, r = next_uniform(state)
    if r < p_incoherent:
        if q_kn >= 0.0:
            e_out, cos_theta = klein_nishina_inverse(e, q_kn)
        else:
            state, e_out, cos_theta = sample_klein_nishina(e, state)
        state, r_phi = next_uniform_or(state, q_phi)
        u2, v2, w2 = rotate_direction(u, v, w, cos_theta, _TWO_PI * r_phi)
        eu, ev, ew = compton_electron_direction(e, e_out, u, v, w, u2, v2, w2)
        return (state, INCOHERENT, e_out, u2, v2, w2, e - e_out, eu, ev, ew,
                0.0, 0.0, 0.0, 0.0)
    state, r_phi = next_uniform(state)
    phi = _TWO_PI * r_phi
    if r < p_incoherent + p_pair and e > 2.0 * ELECTRON_MASS_MEV:
        t_total = e - 2.0 * ELECTRON_MASS_MEV
        state, xi = next_uniform(state)
        t_minus = xi * t_total
        state, c_minus = sample_leading_term_cos(t_minus, state)
        state, c_plus = sample_leading_term_cos(t_total - t_minus, state)
        eu, ev, ew = rotate_direction(u, v, w, c_minus, phi)
        pu, pv, pw = rotate_direction(u, v, w, c_plus, phi + math.pi)
        return (state, PAIR, 0.0, u, v, w, t_minus, eu, ev, ew,
                t_total - t_minus, pu, pv, pw)
    state, cos_e = sample_sauter_cos(e, state)
    eu, ev, ew = rotate_direction(u, v, w, cos_e, phi)
    return state, PHOTOELECTRIC, 0.0, u, v, w, e, eu, ev, ew, 0.0, 0.0, 0.0, 0.0


@njit(cache=True, inline="always")
def release_products(state, kind, t1, eu, ev, ew, t2, pu, pv, pw, x, y, z, cell, e_cut, wt,
                     scheme, tally, ledger, counts, stack, n_stack):
    """:func:`release` the charged particles of an interaction sampled by
    :func:`interaction_products` at (x, y, z) in ``cell``: (state, n_stack)."""
    state, n_stack = release(state, ELECTRON, t1, x, y, z, eu, ev, ew, cell, e_cut, wt, scheme,
                             tally, ledger, counts, stack, n_stack)
    if kind == PAIR:
        state, n_stack = release(state, POSITRON, t2, x, y, z, pu, pv, pw, cell, e_cut, wt,
                                 scheme, tally, ledger, counts, stack, n_stack)
    return state, n_stack


@kernel
def photon_interaction(xs, m, cell, e, u, v, w, state, e_cut, wt, scheme, tally, ledger, counts,
                       stack, n_stack, x, y, z):
    """One photon interaction at (x, y, z) (module docstring): returns
    (state, alive, e, u, v, w, n_stack) of the photon."""
    state, kind, e2, u2, v2, w2, t1, eu, ev, ew, t2, pu, pv, pw = interaction_products(
        xs, m, e, u, v, w, state)
    state, n_stack = release_products(state, kind, t1, eu, ev, ew, t2, pu, pv, pw, x, y, z, cell,
                                      e_cut, wt, scheme, tally, ledger, counts, stack, n_stack)
    return state, kind == INCOHERENT, e2, u2, v2, w2, n_stack
