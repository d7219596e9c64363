"""njit electron history repetition: one electron track sampled in a reference medium, replayed
for the electrons of every copy of a split photon (``splitting_scheme="repeat"``).

**Method** (XVMC: Kawrakow, Fippel & Friedrich, Med. Phys. 23:445, 1996; Kawrakow & Fippel,
PMB 45:2163, 2000; VMC++). The n copies of a split photon (weight 1/n,
:mod:`tetdose.transport.history._split`) interact at their own sites along its ray, but with one
random stream shared by the copies: they all move along one direction with one energy, so each
sets in motion an electron of the same energy T and direction at its own site (where the
material picks the same type). That electron's track is sampled once, in the medium m₀ of the
first site it is needed at, by :func:`record_track` (the physics of
:func:`~tetdose.transport.history._electron.electron_track`, with the same random hinge and
fictitious hard events, but no geometry): per step the mass thicknesses before and after the
hinge s₁, s₂ [mm·g/cm³], the hinge deflection (cos θ, φ) and the energy at its end; per hard
event the δ-ray or bremsstrahlung photon (energy, cos, φ relative to the electron) and the
primary's new energy and deflection. Every copy then replays it (:func:`replay_track`) from its
own site, with its weight 1/n: each step walks the real geometry (voxels, linear-density tets,
hybrid; :func:`~._segment.segment` moves a given mass thickness) and deposits the step's energy
loss along it; δ-rays are pushed with weight 1/n and transported, photons play Russian roulette
(survival 1/n). The track is a fresh sample for every split photon, so each copy's electron is,
on its own, an analog track: the dose is unbiased (the copies are correlated, which is what the
saved electron transport costs).

**Scaling to the local medium** (XVMC's eqs. for step length and deflection): in a medium m ≠
m₀ a step of mass thickness s₀ becomes s = s₀ / f_c with f_c = S_m(Ē)/S_m₀(Ē) the restricted
stopping-power ratio at the step's mean energy (the same energy loss), and its deflection angle
θ = θ₀ √(f_s / f_c), f_s = λ₁⁻¹_m(Ē)/λ₁⁻¹_m₀(Ē) the ratio of first transport cross sections
(the angular variance ∝ s/λ₁); a step crossing media is scaled piece by piece. In m₀ itself
(any density: mass thicknesses) the replay is the analog track exactly; elsewhere the scaling is
XVMC's approximation, tested against the analog dose in a lung slab. Positrons are never
replayed. A track longer than the buffer deposits its remaining energy where the replay stops
(counted with the stack overflows). The dose-to-water sums (``dw``,
:class:`~tetdose.transport.history._electron.WaterTally`) take every replayed piece in its own
medium at the step's mean energy, and the replayed track's end.
"""

import math

from numba import njit

from tetdose._constants import MM_PER_CM
from tetdose._jit import kernel
from tetdose._random import next_uniform
from tetdose.transport.geometry._world import cell_material
from tetdose.transport.history._electron import (
    C_E_STEPS,
    C_E_TRACKS,
    ELECTRON,
    L_E_DEPOSITED,
    L_E_ESCAPED,
    MAX_IDLE_STEPS,
    deposit_step,
    push_weighted,
    roulette_photon,
    sigma_majorant,
    stop_charged,
    water_end,
    water_step,
)
from tetdose.transport.history._photon import C_LOST, C_STACK_FULL, L_LOST
from tetdose.transport.history._segment import SEG_DONE, SEG_ESCAPED, SEG_LOST, segment
from tetdose.transport.physics._electron import (
    energy_at_range,
    hard_cross_sections,
    lambda1_inverse,
    range_of,
    sample_brems,
    sample_moller,
    sample_ms_cos,
    stopping_power,
)
from tetdose.transport.physics._photon import rotate_cs

#: Row kinds of a recorded track: a step (s₁, cos θ, cos φ, sin φ, s₂, E_end), a δ-ray (T, cos,
#: cos φ, sin φ), a photon (k, cos, cos φ, sin φ), the primary after a hard event (E, cos, cos φ,
#: sin φ). The azimuth is stored as (cos φ, sin φ): every copy's replay rotates by it.
R_STEP, R_DELTA, R_PHOTON, R_TURN = 0, 1, 2, 3
#: Rows and columns of the track buffer; key: (T, u, v, w, m₀, rows) of the track it holds.
TRACK_ROWS = 2048
TRACK_COLUMNS = 7
KEY_SIZE = 6
_TWO_PI = 2.0 * math.pi


@kernel
def _row(trk, n, kind, a, cos_theta, phi, b, c):
    r = trk[n]
    r[0], r[1], r[2], r[3], r[4], r[5], r[6] = (kind, a, cos_theta, math.cos(phi), math.sin(phi),
                                                b, c)
    return n + 1


@kernel
def record_hard(et, m, e, s_hat, state, trk, n):
    """Real or fictitious hard event of an electron (as ``_electron.hard_event``), recorded:
    (state, rows, e)."""
    s_delta, s_brems, _ = hard_cross_sections(et, m, ELECTRON, e)
    state, xi = next_uniform(state)
    r = xi * s_hat
    if r >= s_delta + s_brems:
        return state, n, e
    state, x_phi = next_uniform(state)
    phi = _TWO_PI * x_phi
    if r < s_delta:
        state, t, cos_p, cos_d = sample_moller(e, et.cutoff_mev, state)
        n = _row(trk, n, R_DELTA, t, cos_d, phi + math.pi, 0.0, 0.0)
        return state, _row(trk, n, R_TURN, e - t, cos_p, phi, 0.0, 0.0), e - t
    state, k, cos_k = sample_brems(et, m, ELECTRON, e, state)
    n = _row(trk, n, R_PHOTON, k, cos_k, phi, 0.0, 0.0)
    return state, _row(trk, n, R_TURN, e - k, 1.0, 0.0, 0.0, 0.0), e - k


@kernel
def record_track(et, sig_hat, m, e, state, f_loss, trk):
    """Sample an electron track of kinetic energy ``e`` [MeV] in an unbounded medium ``m`` into
    ``trk`` (module docstring): (state, rows)."""
    e_cut = et.cutoff_mev
    n = 0
    while e > e_cut and n < trk.shape[0] - 3:
        r0 = range_of(et, m, ELECTRON, e)
        e_lo = e * (1.0 - f_loss)
        stops = e_lo <= e_cut
        s_loss = r0 if stops else max(r0 - range_of(et, m, ELECTRON, e_lo), 0.0)
        s_hat = sigma_majorant(sig_hat, et, m, ELECTRON, e)
        state, xi = next_uniform(state)
        s_hard = -math.log(1.0 - xi) / s_hat if s_hat > 0.0 else math.inf
        hard = s_hard < s_loss
        s = s_hard if hard else s_loss
        state, xh = next_uniform(state)
        e_end = e_cut if (stops and not hard) else energy_at_range(et, m, ELECTRON, r0 - s)
        e_end = min(max(e_end, 0.0), e)
        state, mu = sample_ms_cos(et, m, ELECTRON, 0.5 * (e + e_end), s, state)
        state, x_phi = next_uniform(state)
        n = _row(trk, n, R_STEP, xh * s * MM_PER_CM, mu, _TWO_PI * x_phi,
                 (1.0 - xh) * s * MM_PER_CM, e_end)
        e = e_end
        if hard and e > e_cut:
            state, n, e = record_hard(et, m, e, s_hat, state, trk, n)
    return state, n


@kernel
def scaled_cos(et, m0, m, e, mu):
    """cos θ of a deflection θ₀ = acos ``mu`` sampled in m₀, replayed in m: θ₀ √(f_s/f_c)."""
    if m == m0:
        return mu
    f_c = stopping_power(et, m, ELECTRON, e) / stopping_power(et, m0, ELECTRON, e)
    f_s = lambda1_inverse(et, m, ELECTRON, e) / lambda1_inverse(et, m0, ELECTRON, e)
    theta = math.acos(min(max(mu, -1.0), 1.0)) * math.sqrt(f_s / f_c)
    return -1.0 if theta >= math.pi else math.cos(theta)


@njit(cache=True, inline="always")
def replay_move(wg, et, m0, e_mid, col0, de, wt, cell, entry, x, y, z, u, v, w, tally, ledger,
                counts, bcell, bcol, dw):
    """Move the reference column ``col0`` [mm·g/cm³ of m₀] straight through the world, each
    piece in medium m scaled by 1/f_c, and deposit wt × ``de`` along it in proportion to the
    reference column: (outcome, cell, entry, x, y, z, energy deposited [MeV, unweighted])."""
    s0 = -1.0
    left, dep, idle = col0, 0.0, 0
    while True:
        m = cell_material(wg, cell)
        f_c = 1.0
        if m != m0:
            if s0 < 0.0:
                s0 = stopping_power(et, m0, ELECTRON, e_mid)
            f_c = stopping_power(et, m, ELECTRON, e_mid) / s0
        out, cell2, entry2, x, y, z, rest, nb = segment(wg, cell, entry, x, y, z, u, v, w,
                                                        left / f_c, m, bcell, bcol, 0, counts)
        done = left / f_c - rest
        part = de - dep if out == SEG_DONE or col0 <= 0.0 else min(de * done * f_c / col0,
                                                                   de - dep)
        deposit_step(part * wt, bcell, bcol, nb, done, tally, cell)
        if dw.a.shape[0] > 0:
            water_step(dw, et, m, ELECTRON, e_mid, wt, bcell, bcol, nb)
        ledger[L_E_DEPOSITED] += part * wt
        dep += part
        left -= done * f_c
        idle = idle + 1 if done <= 0.0 else 0
        if out == SEG_DONE or out == SEG_ESCAPED or out == SEG_LOST:
            return out, cell2, entry2, x, y, z, dep
        if idle > MAX_IDLE_STEPS:
            return SEG_LOST, cell2, entry2, x, y, z, dep
        cell, entry = cell2, entry2


@njit(cache=True, inline="always")
def replay_track(wg, et, trk, n_rows, m0, e, cell, x, y, z, u, v, w, wt, state, tally, ledger,
                 counts, stack, n_stack, bcell, bcol, dw):
    """Replay the recorded electron track ``trk`` (sampled in m₀) from global ``cell`` along
    (u, v, w) with weight ``wt`` (module docstring): (state, n_stack)."""
    counts[C_E_TRACKS] += 1
    entry = -1
    for i in range(n_rows):
        r = trk[i]
        kind = int(r[0])
        if kind == R_STEP:
            de, e_mid = e - r[6], 0.5 * (e + r[6])
            de1 = de * r[1] / (r[1] + r[5]) if r[1] + r[5] > 0.0 else 0.0
            out, cell, entry, x, y, z, dep = replay_move(wg, et, m0, e_mid, r[1], de1, wt, cell,
                                                         entry, x, y, z, u, v, w, tally, ledger,
                                                         counts, bcell, bcol, dw)
            if out == SEG_DONE:
                m = cell_material(wg, cell)
                mu = r[2] if m == m0 else scaled_cos(et, m0, m, e_mid, r[2])
                u, v, w = rotate_cs(u, v, w, mu, r[3], r[4])
                out, cell, entry, x, y, z, dep2 = replay_move(
                    wg, et, m0, e_mid, r[5], de - de1, wt, cell, -1, x, y, z, u, v, w, tally,
                    ledger, counts, bcell, bcol, dw)
                dep += dep2
            counts[C_E_STEPS] += 1
            if out == SEG_ESCAPED:
                ledger[L_E_ESCAPED] += (e - dep) * wt
                return state, n_stack
            if out != SEG_DONE:
                ledger[L_LOST] += (e - dep) * wt
                counts[C_LOST] += 1
                return state, n_stack
            e = r[6]
        elif kind == R_DELTA:
            du, dv, dz = rotate_cs(u, v, w, r[2], r[3], r[4])
            n_stack = push_weighted(stack, n_stack, ELECTRON, r[1], x, y, z, du, dv, dz, cell,
                                    wt, tally, ledger, counts)
        elif kind == R_PHOTON:
            ku, kv, kw = rotate_cs(u, v, w, r[2], r[3], r[4])
            state, n_stack = roulette_photon(state, r[1], x, y, z, ku, kv, kw, cell, wt, tally,
                                             ledger, counts, stack, n_stack)
        else:
            e = r[1]
            if r[2] < 1.0:
                u, v, w = rotate_cs(u, v, w, r[2], r[3], r[4])
                entry = -1
    if e > et.cutoff_mev:
        counts[C_STACK_FULL] += 1  # the track outgrew the buffer: the rest stays here
    if dw.a.shape[0] > 0:
        water_end(dw, et, cell_material(wg, cell), ELECTRON, e, wt, cell)
    return stop_charged(state, ELECTRON, e, x, y, z, cell, wt, tally, ledger, counts, stack,
                        n_stack)


@kernel
def repeat_electron(wg, et, sig_hat, e, cell, x, y, z, u, v, w, wt, state, f_loss, tally, ledger,
                    counts, stack, n_stack, bcell, bcol, trk, key, dw):
    """An electron of a split photon's copy: the track in ``trk`` if ``key`` says it is this
    electron's (same T and direction: the copies share their interaction), else a new one
    sampled in the medium here; then replayed from here (module docstring; ``dw`` the
    dose-to-water sums)."""
    if not (key[0] == e and key[1] == u and key[2] == v and key[3] == w):
        m0 = cell_material(wg, cell)
        state, n_rows = record_track(et, sig_hat, m0, e, state, f_loss, trk)
        key[0], key[1], key[2], key[3], key[4], key[5] = e, u, v, w, m0, n_rows
    return replay_track(wg, et, trk, int(key[5]), int(key[4]), e, cell, x, y, z, u, v, w, wt,
                        state, tally, ledger, counts, stack, n_stack, bcell, bcol, dw)
