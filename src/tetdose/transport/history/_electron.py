"""njit condensed-history (class II) electron and positron tracks in the world.

**Step.** All lengths are mass thicknesses s [g/cm²], so the scheme depends on the density only
through where a mass thickness ends (the Fano condition; see below). From kinetic energy E in
material m a step is the shortest of

- the distance to the next hard event (Møller/Bhabha δ-ray above the cut-off, bremsstrahlung
  above the photon cut-off, positron annihilation in flight), sampled with a majorant:
  s_hard = −ln(1 − ξ)/σ̂, where σ̂ ≥ σ(E') for every E' the step can reach (table ``sig_hat``,
  the maximum of σ_δ + σ_brems + σ_annih over the energy window [E(1 − f), E] on the grid
  nodes); at the step's end the event is real with probability σ(E_end)/σ̂, else fictitious
  (the "fictitious interaction" method of EGSnrc and PENELOPE, exact for energy-dependent σ);
- the mass thickness over which the restricted CSDA loss takes a fraction f of E
  (``max_energy_loss_fraction``, EGSnrc's ESTEPE): s_loss = R(E) − R(E(1 − f)), or R(E) when
  E(1 − f) is below the cut-off (the track ends there);
- the end of the material: a segment stops at a cell of another material or at the buffer's end
  (:mod:`tetdose.transport.history._segment`), and the step ends there.

**Random hinge** (Kawrakow & Bielajew, NIM B 142:253, 1998; PENELOPE): the electron moves ξ·s
straight, is deflected by the multiple-scattering angle of the whole step (``sample_ms_cos`` for
s at the step's mean energy (E + E_end)/2, azimuth uniform), then moves (1 − ξ)·s. A segment cut
short ends the step there, without the deflection if the hinge was not reached.

**Energy loss.** E_end = R⁻¹(R(E) − s_done) from the restricted range table (CSDA, continuous
collision + soft radiative loss); E − E_end is shared among the cells the step crossed in
proportion to the mass thickness in each (the last cell takes the rounding remainder, so the
energy is conserved exactly). Below the cut-off an electron deposits its kinetic energy where it
stops; a positron too, then annihilates at rest: two photons of mc² back to back, isotropic.

**Fano.** Every step length, deflection and energy loss depends on (E, s) only, the hinge on s;
along any straight line the mass coordinate maps a medium of one composition and any density
onto a homogeneous one, so a source uniform per unit mass gives a dose uniform per unit mass
away from the outer surface, whatever the density pattern (tets with linear density, steps,
voxels, vacuum gaps). The cases that shorten a step at a position (a material change, the outer
surface, a full buffer) are the only departures; the first two do not occur inside a region of
one composition.

**Ledger** (dose mode, MeV, columns after the photon ones of :mod:`._photon`): continuous loss
deposited (L_E_DEPOSITED), e± escaped (L_E_ESCAPED), e± kinetic energy deposited below the cut-off
(L_E_CUTOFF), and the net energy Russian roulette removed (L_ROULETTE: the weight × energy of the
charged particles it killed minus the energy it gave the survivors; zero on average, see
:mod:`tetdose.transport.history._coupled`). A positron's energy in the ledger is T + 2mc² (its
kinetic energy and the annihilation energy it releases: in pair production E = T₋ + (T₊ + 2mc²));
its annihilation photons then carry the 2mc² on.

**Weighted tracks** (photon splitting that follows the electrons,
:mod:`tetdose.transport.history._coupled`): a track of statistical weight w < 1 deposits w times
every energy loss and pushes its δ-rays with weight w; the photons it creates (bremsstrahlung,
annihilation in flight and at rest) play Russian roulette — each survives with probability w and
then carries weight 1, else it is killed (ledger L_ROULETTE: + w·k killed, − (1 − w)·k
survivor). E[weight × energy] is the analog one for every particle, so every tally is unbiased.
A track of weight 1 draws no roulette number: the analog track bit for bit.

**Dose to water** (Spencer–Attix cavity theory over the fluence each cell tracks; Siebers,
Keall, Nahum & Mohan, PMB 45:983, 2000; Nahum, PMB 23:24, 1978): with a :class:`WaterTally` of
non-empty sums, every step of mass thickness s_c [g/cm²] in cell c (the buffered cells of the
step, medium m) adds A_c += wt·s_c·L_w(Ē) and B_c += wt·s_c·L_m(Ē), Ē = (E + E_end)/2 and L
the tables' restricted total stopping power (collision below Δ plus radiative below k_c, the
one the tracks lose energy by); a track end (an e± stopping below Δ, or a range-rejected
track) of kinetic energy T adds the track-end term B_c += wt·T, A_c += wt·T·L_w(T)/L_m(T).
Then s_w,m(c) = A_c/B_c. Water's row is a separate table on the same grid, looked up the same
way, so in water A_c == B_c bitwise. Empty sums (dose to medium): nothing is looked up.
"""

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from tetdose._constants import MM_PER_CM
from tetdose._jit import kernel
from tetdose._random import next_uniform
from tetdose.transport.geometry._world import cell_material
from tetdose.transport.history._photon import C_LOST, C_STACK_FULL, L_CUTOFF, L_LOST
from tetdose.transport.history._segment import (
    SEG_DONE,
    SEG_ESCAPED,
    SEG_LOST,
    segment,
)
from tetdose.transport.physics._electron import (
    electron_position,
    energy_at_range,
    hard_cross_sections,
    range_of,
    sample_annihilation_in_flight,
    sample_bhabha,
    sample_brems,
    sample_moller,
    sample_ms_cos,
)
from tetdose.transport.physics._photon import isotropic_direction, rotate_direction

#: Species codes (the tables' index for e∓; photons on the same stack; an electron whose track
#: is replayed, :mod:`._repeat`).
ELECTRON, POSITRON, PHOTON, REPLAY = 0, 1, 2, 3
#: Electron rest energy [MeV] (CODATA 2018).
ELECTRON_MASS_MEV = 0.51099895
#: Dose-mode ledger columns after the photon ones, and the counters after the photon ones.
L_E_DEPOSITED, L_E_ESCAPED, L_E_CUTOFF, L_ROULETTE = 5, 6, 7, 8
N_LEDGER_DOSE = 9
C_E_STEPS, C_E_TRACKS = 7, 8
#: Tentative collisions of the photons' Woodcock flights (:mod:`._delta`).
C_DELTA_STEPS = 9
N_COUNTS_DOSE = 10
#: Columns of a stack row: energy, x, y, z, u, v, w, cell, species, statistical weight.
STACK_COLUMNS = 10
#: Steps in a row that move no mass thickness before the track is counted lost.
MAX_IDLE_STEPS = 1000
_TWO_PI = 2.0 * math.pi


class WaterTally(NamedTuple):
    """Spencer–Attix sums of a batch (module docstring): ``stopping`` (2, n_e) water's L/ρ
    [MeV cm²/g] on the electron tables' grid; ``a``, ``b`` (n_cells,) Σ wt·s·L_w and Σ wt·s·L_m
    [MeV] (size 0: not tallied)."""

    stopping: np.ndarray
    a: np.ndarray
    b: np.ndarray


@kernel
def water_step(dw, et, m, sp, e_mid, wt, bcell, bcol, nb):
    """Add one step of mean energy ``e_mid`` [MeV] in medium m, over the ``nb`` buffered cells
    with columns ``bcol`` [mm·g/cm³], to the sums ``dw`` (module docstring)."""
    i, f = electron_position(et, e_mid)
    lw = (1.0 - f) * dw.stopping[sp, i] + f * dw.stopping[sp, i + 1]
    lm = (1.0 - f) * et.stopping[m, sp, i] + f * et.stopping[m, sp, i + 1]
    for k in range(nb):
        s = wt * bcol[k] / MM_PER_CM
        dw.a[bcell[k]] += s * lw
        dw.b[bcell[k]] += s * lm


@kernel
def water_end(dw, et, m, sp, e, wt, cell):
    """Add the track-end term of kinetic energy ``e`` [MeV] deposited at once in ``cell`` of
    medium m to the sums ``dw`` (module docstring)."""
    i, f = electron_position(et, e)
    lw = (1.0 - f) * dw.stopping[sp, i] + f * dw.stopping[sp, i + 1]
    lm = (1.0 - f) * et.stopping[m, sp, i] + f * et.stopping[m, sp, i + 1]
    dw.a[cell] += wt * e * (lw / lm)
    dw.b[cell] += wt * e


@kernel
def push(stack, n_stack, species, e, x, y, z, u, v, w, cell, tally, ledger, counts):
    """Push a particle of weight 1 (energy [MeV]: kinetic for e±) on the stack; on a full stack
    deposit it in ``cell`` instead (a positron with its annihilation energy) and count the
    overflow."""
    if n_stack < stack.shape[0]:
        r = stack[n_stack]
        r[0], r[1], r[2], r[3], r[4], r[5], r[6] = e, x, y, z, u, v, w
        r[7] = cell
        r[8] = species
        r[9] = 1.0
        return n_stack + 1
    counts[C_STACK_FULL] += 1
    if species == PHOTON:
        ledger[L_CUTOFF] += e
    else:
        e += 2.0 * ELECTRON_MASS_MEV if species == POSITRON else 0.0
        ledger[L_E_CUTOFF] += e
    tally[cell] += e
    return n_stack


@kernel
def push_weighted(stack, n_stack, sp, e, x, y, z, u, v, w, cell, wt, tally, ledger, counts):
    """Push a particle of weight ``wt`` on the stack; on a full stack deposit wt × its energy in
    ``cell`` (a positron with its annihilation energy) and count the overflow."""
    if n_stack < stack.shape[0]:
        r = stack[n_stack]
        r[0], r[1], r[2], r[3], r[4], r[5], r[6] = e, x, y, z, u, v, w
        r[7] = cell
        r[8] = sp
        r[9] = wt
        return n_stack + 1
    counts[C_STACK_FULL] += 1
    if sp == PHOTON:
        ledger[L_CUTOFF] += e * wt
    else:
        e += 2.0 * ELECTRON_MASS_MEV if sp == POSITRON else 0.0
        ledger[L_E_CUTOFF] += e * wt
    tally[cell] += e * wt
    return n_stack


@njit(cache=True, inline="always")
def roulette_survives(state, wt, e, ledger):
    """Russian roulette of a particle of weight ``wt`` < 1 carrying energy ``e`` [MeV]: it
    survives with probability wt (then weight 1); ledger L_ROULETTE + wt·e if killed,
    − (1 − wt)·e if it survives (module docstring). Returns (state, survives)."""
    state, xi = next_uniform(state)
    if xi >= wt:
        ledger[L_ROULETTE] += wt * e
        return state, False
    ledger[L_ROULETTE] -= (1.0 - wt) * e
    return state, True


@kernel
def roulette_photon(state, k, x, y, z, u, v, w, cell, wt, tally, ledger, counts, stack,
                    n_stack):
    """A photon of energy k [MeV] created by a particle of weight ``wt``: pushed with weight 1,
    after Russian roulette (survival wt) if wt < 1 (module docstring)."""
    if wt < 1.0:
        state, survives = roulette_survives(state, wt, k, ledger)
        if not survives:
            return state, n_stack
    return state, push(stack, n_stack, PHOTON, k, x, y, z, u, v, w, cell, tally, ledger, counts)


@kernel
def annihilate_at_rest(state, stack, n_stack, x, y, z, cell, wt, tally, ledger, counts):
    """Two photons of mc² back to back in an isotropic direction, pushed on the stack (after
    roulette if the positron's weight ``wt`` < 1)."""
    state, u, v, w = isotropic_direction(state)
    state, n_stack = roulette_photon(state, ELECTRON_MASS_MEV, x, y, z, u, v, w, cell, wt, tally,
                                     ledger, counts, stack, n_stack)
    return roulette_photon(state, ELECTRON_MASS_MEV, x, y, z, -u, -v, -w, cell, wt, tally,
                           ledger, counts, stack, n_stack)


@kernel
def stop_charged(state, sp, e, x, y, z, cell, wt, tally, ledger, counts, stack, n_stack):
    """An e± of weight ``wt`` below the cut-off: wt × its kinetic energy stays in ``cell``; a
    positron annihilates."""
    tally[cell] += e * wt
    ledger[L_E_CUTOFF] += e * wt
    if sp == POSITRON:
        state, n_stack = annihilate_at_rest(state, stack, n_stack, x, y, z, cell, wt, tally,
                                            ledger, counts)
    return state, n_stack


@njit(cache=True, inline="always")
def deposit_step(de, bcell, bcol, nb, col_done, tally, cell):
    """Share ``de`` [MeV] among the buffered cells in proportion to their column (the last one
    takes the remainder, so Σ = de exactly); all in ``cell`` if nothing was crossed."""
    if nb == 0 or col_done <= 0.0:
        tally[cell] += de
        return
    rest = de
    for i in range(nb - 1):
        part = de * (bcol[i] / col_done)
        tally[bcell[i]] += part
        rest -= part
    tally[bcell[nb - 1]] += rest


@kernel
def sigma_majorant(sig_hat, et, m, sp, e):
    """σ̂ [cm²/g] of the step from energy e (piecewise constant on the table's grid)."""
    i, _f = electron_position(et, e)
    return sig_hat[m, sp, i]


@kernel
def hard_event(et, m, sp, e, s_hat, x, y, z, u, v, w, cell, wt, state, tally, ledger, counts,
               stack, n_stack):
    """Real or fictitious hard event at the end of a step of a track of weight ``wt`` (see
    module): returns (state, alive, e, u, v, w, n_stack) of the primary."""
    s_delta, s_brems, s_annih = hard_cross_sections(et, m, sp, e)
    state, xi = next_uniform(state)
    r = xi * s_hat
    if r >= s_delta + s_brems + s_annih:
        return state, True, e, u, v, w, n_stack  # fictitious
    state, x_phi = next_uniform(state)
    phi = _TWO_PI * x_phi
    if r < s_delta:
        if sp == ELECTRON:
            state, t, cos_p, cos_d = sample_moller(e, et.cutoff_mev, state)
        else:
            state, t, cos_p, cos_d = sample_bhabha(e, et.cutoff_mev, state)
        du, dv, dw = rotate_direction(u, v, w, cos_d, phi + math.pi)
        n_stack = push_weighted(stack, n_stack, ELECTRON, t, x, y, z, du, dv, dw, cell, wt,
                                tally, ledger, counts)
        u, v, w = rotate_direction(u, v, w, cos_p, phi)
        return state, True, e - t, u, v, w, n_stack
    if r < s_delta + s_brems:
        state, k, cos_k = sample_brems(et, m, sp, e, state)
        ku, kv, kw = rotate_direction(u, v, w, cos_k, phi)
        state, n_stack = roulette_photon(state, k, x, y, z, ku, kv, kw, cell, wt, tally, ledger,
                                         counts, stack, n_stack)
        return state, True, e - k, u, v, w, n_stack
    state, k1, c1, k2, c2 = sample_annihilation_in_flight(e, state)
    ku, kv, kw = rotate_direction(u, v, w, c1, phi)
    state, n_stack = roulette_photon(state, k1, x, y, z, ku, kv, kw, cell, wt, tally, ledger,
                                     counts, stack, n_stack)
    ku, kv, kw = rotate_direction(u, v, w, c2, phi + math.pi)
    state, n_stack = roulette_photon(state, k2, x, y, z, ku, kv, kw, cell, wt, tally, ledger,
                                     counts, stack, n_stack)
    return state, False, 0.0, u, v, w, n_stack


@kernel
def electron_track(wg, et, sig_hat, sp, e, cell, x, y, z, u, v, w, wt, state, f_loss, tally,
                   ledger, counts, stack, n_stack, bcell, bcol, dw):
    """Follow one e⁻ (sp = 0) or e⁺ (sp = 1) of kinetic energy ``e`` [MeV] and statistical
    weight ``wt`` from global ``cell`` to its end (module docstring); its secondaries go on the
    stack; ``dw`` the dose-to-water sums (:class:`WaterTally`). Returns (state, n_stack)."""
    e_cut = et.cutoff_mev
    rest = 2.0 * ELECTRON_MASS_MEV if sp == POSITRON else 0.0
    counts[C_E_TRACKS] += 1
    entry = -1
    idle = 0
    water = dw.a.shape[0] > 0
    while True:
        if e <= e_cut:
            if water:
                water_end(dw, et, cell_material(wg, cell), sp, e, wt, cell)
            return stop_charged(state, sp, e, x, y, z, cell, wt, tally, ledger, counts, stack,
                                n_stack)
        m = cell_material(wg, cell)
        r0 = range_of(et, m, sp, e)
        e_lo = e * (1.0 - f_loss)
        stops = e_lo <= e_cut
        s_loss = r0 if stops else max(r0 - range_of(et, m, sp, e_lo), 0.0)
        s_hat = sigma_majorant(sig_hat, et, m, sp, e)
        state, xi = next_uniform(state)
        s_hard = -math.log(1.0 - xi) / s_hat if s_hat > 0.0 else math.inf
        hard = s_hard < s_loss
        s = s_hard if hard else s_loss
        state, xh = next_uniform(state)
        col1 = xh * s * MM_PER_CM
        out, cell2, entry2, x, y, z, left, nb = segment(wg, cell, entry, x, y, z, u, v, w, col1,
                                                        m, bcell, bcol, 0, counts)
        col_done = col1 - left
        complete = False
        e_full = e
        if out == SEG_DONE:
            e_full = e_cut if (stops and not hard) else energy_at_range(et, m, sp, r0 - s)
            state, mu = sample_ms_cos(et, m, sp, 0.5 * (e + e_full), s, state)
            state, x_phi = next_uniform(state)
            u, v, w = rotate_direction(u, v, w, mu, _TWO_PI * x_phi)
            col2 = s * MM_PER_CM - col1
            out, cell2, entry2, x, y, z, left, nb = segment(wg, cell2, -1, x, y, z, u, v, w,
                                                            col2, m, bcell, bcol, nb, counts)
            col_done = col1 + col2 - left
            complete = out == SEG_DONE
        if complete:
            e_end = e_full
        elif col_done > 0.0:
            e_end = energy_at_range(et, m, sp, max(r0 - col_done / MM_PER_CM, 0.0))
        else:
            e_end = e
        e_end = min(max(e_end, 0.0), e)
        deposit_step((e - e_end) * wt, bcell, bcol, nb, col_done, tally, cell)
        if water:
            water_step(dw, et, m, sp, 0.5 * (e + e_end), wt, bcell, bcol, nb)
        ledger[L_E_DEPOSITED] += (e - e_end) * wt
        counts[C_E_STEPS] += 1
        e = e_end
        idle = idle + 1 if col_done <= 0.0 else 0
        if out == SEG_ESCAPED:
            ledger[L_E_ESCAPED] += (e + rest) * wt
            return state, n_stack
        if out == SEG_LOST or idle > MAX_IDLE_STEPS:
            ledger[L_LOST] += (e + rest) * wt
            counts[C_LOST] += 1
            return state, n_stack
        cell, entry = cell2, entry2
        if complete and hard and e > e_cut:
            state, alive, e, u2, v2, w2, n_stack = hard_event(
                et, m, sp, e, s_hat, x, y, z, u, v, w, cell, wt, state, tally, ledger, counts,
                stack, n_stack)
            if not alive:
                return state, n_stack
            if u2 != u or v2 != v or w2 != w:
                entry = -1
            u, v, w = u2, v2, w2
