"""njit coupled photon–electron histories (dose mode): photons set electrons in motion.

Photon flights through the mesh are Woodcock (delta) tracked by default (a majorant, point
location, no tet walk: :mod:`tetdose.transport.history._delta`); with
``photon_tracking="walk"`` they are those of kerma mode
(:func:`tetdose.transport.history._photon.flight`, exact free paths in linear density, no
track-length tally). Both are exact. The interaction is chosen from the same
branching fractions as :func:`tetdose.transport.physics._photon.interact`, but the charged
particles it releases are transported instead of depositing their energy where they are born
(:mod:`tetdose.transport.physics._photon_electrons` gives their energies and directions):

- incoherent: the photon continues with E' (Klein–Nishina), the recoil electron T = E − E' goes
  along p = E·d − E'·d';
- photoelectric: the photon is absorbed, a photo-electron T = E goes at the Sauter angle;
- pair (E > 2mc²): the photon is absorbed, an electron and a positron share E − 2mc² uniformly,
  each at its leading-term angle, at opposite azimuths.

A charged particle born below the electron cut-off deposits its kinetic energy there (a positron
then annihilates at rest); a photon below the photon cut-off deposits its energy where it is.
Every particle waits on one stack (LIFO) of rows ``(E, x, y, z, u, v, w, cell, species, weight)``;
the dose is the analog energy deposition (the track-length kerma estimator does not apply), each
deposit times the statistical weight of the particle that makes it.

**Photon splitting with charged-particle Russian roulette** (the scheme of EGSnrc's BEAMnrc
uniform bremsstrahlung splitting and of ompMC's ``n_split``; Kawrakow, Rogers & Walters, Med. Phys.
31:2883, 2004, sec. II.A): a source photon is followed as ``n_split`` independent copies of
weight w = 1/n_split (each its own flight and interactions from the same history's stream). The
photons a copy scatters keep its weight; every electron or positron it sets in motion above the
cut-off plays Russian roulette: it survives with probability w and then carries weight 1, else it
is killed. The expected weight × energy of every particle is the analog one, so every tally is
unbiased; electrons (the costly part) are as many as without splitting, while the photon
interactions that create them — the main source of variance of a dose far from the surface — are
sampled n_split times as densely. Charged particles born below the cut-off deposit w × T where
they are born (no roulette: it would add variance and save nothing); a positron among them gives
annihilation photons of weight w. Every particle an electron creates (δ-rays, bremsstrahlung,
annihilation) has weight 1, so electron tracks never carry a weight. The roulette's energy
balance is the ledger column L_ROULETTE: + w·E for a killed particle, − (1 − w)·E for a survivor
(E = T, + 2mc² for a positron), so deposited + escaped + cut off + lost + roulette = source
exactly in every history, and the roulette column averages to zero.

**XVMC's splitting** (``splitting_scheme="follow"``; Kawrakow & Fippel, PMB 45:2163, 2000,
sec. 2.3): the copies of weight w = 1/n_split are made the same way, but every electron or
positron a copy sets in motion is followed with weight w (not rouletted), its deposits and
δ-rays weighted w; the photons of weight w < 1 that scatter, and every photon a weighted
electron creates (bremsstrahlung, annihilation), play Russian roulette instead: survival w,
then weight 1, so photons never carry a weight for long and the photon shower stays as cheap
as without splitting (:mod:`tetdose.transport.history._electron`). Ledger as above. Alone it
multiplies the electrons by n_split (gain ≈ 1: measured, bench/bench_vr.py); with
``"repeat"`` the copies share their first interaction and one electron track, replayed from
each copy's site (XVMC's electron history repetition, :mod:`tetdose.transport.history._repeat`).

**Range rejection** (EGSnrc's ESAVE, restricted to what cannot change a tally): an electron of
kinetic energy T ≤ ``rr_mev`` starting a track in a cell it cannot leave deposits T there at
once. In a voxel (density ρ constant) it cannot leave when R(T)·10 < d·ρ, d [mm] the distance to
the nearest wall. In a tet it cannot when R(T)·10 < d·(ρ(p) − |∇ρ|·d), d the distance to the
nearest face plane: the ball of radius d about p lies inside the (convex) tet, the first d of
any path to a face lies in that ball, and the linear density there is at least ρ(p) − |∇ρ|·d.
Every charged descendant stays inside: a step of mass thickness p leaves
R(T') = R(T) − p, and a hard event shares T' between two particles of ranges below R(T'), so no
electron path from the start is longer than R(T) and the straight distance is shorter still. The
one approximation is the hard bremsstrahlung photons (k > k_c) the track would have sent away:
their energy, the radiative yield Y(T) · T (≤ 0.4 % of T in water below 1 MeV, ESTAR), stays in
the cell instead. Positrons (their annihilation photons) and voxels listing mesh triangles (a tet
may be nearer) are never rejected.
"""

import math

from tetdose._constants import MM_PER_CM
from tetdose._jit import kernel
from tetdose._random import next_uniform
from tetdose.transport.geometry._tet import density_at
from tetdose.transport.geometry._world import cell_material, voxel_ijk
from tetdose.transport.history._delta import flight_delta
from tetdose.transport.history._electron import (
    C_E_TRACKS,
    ELECTRON,
    ELECTRON_MASS_MEV,
    L_E_CUTOFF,
    L_ROULETTE,
    PHOTON,
    POSITRON,
    REPLAY,
    electron_track,
    push,
    push_weighted,
    stop_charged,
    water_end,
)
from tetdose.transport.history._photon import (
    C_LOST,
    ESCAPES,
    L_CUTOFF,
    L_ESCAPED,
    L_LOST,
    LOST,
    flight,
)
from tetdose.transport.history._repeat import repeat_electron
from tetdose.transport.physics._electron import range_of
from tetdose.transport.physics._photon import (
    branching_fractions,
    isotropic_direction,
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


@kernel
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
            state, xi = next_uniform(state)
            if xi >= wt:
                ledger[L_ROULETTE] += wt * e_ledger
                return state, n_stack
            ledger[L_ROULETTE] -= (1.0 - wt) * e_ledger
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
def photon_interaction(xs, m, cell, e, u, v, w, state, e_cut, wt, scheme, tally, ledger, counts,
                       stack, n_stack, x, y, z):
    """One photon interaction at (x, y, z) (module docstring): returns
    (state, alive, e, u, v, w, n_stack) of the photon."""
    p_incoherent, p_pair = branching_fractions(xs, m, e)
    state, r = next_uniform(state)
    if r < p_incoherent:
        state, e_out, cos_theta = sample_klein_nishina(e, state)
        state, r_phi = next_uniform(state)
        u2, v2, w2 = rotate_direction(u, v, w, cos_theta, _TWO_PI * r_phi)
        eu, ev, ew = compton_electron_direction(e, e_out, u, v, w, u2, v2, w2)
        state, n_stack = release(state, ELECTRON, e - e_out, x, y, z, eu, ev, ew, cell, e_cut,
                                 wt, scheme, tally, ledger, counts, stack, n_stack)
        return state, True, e_out, u2, v2, w2, n_stack
    state, r_phi = next_uniform(state)
    phi = _TWO_PI * r_phi
    if r < p_incoherent + p_pair and e > 2.0 * ELECTRON_MASS_MEV:
        t_total = e - 2.0 * ELECTRON_MASS_MEV
        state, xi = next_uniform(state)
        t_minus = xi * t_total
        state, c_minus = sample_leading_term_cos(t_minus, state)
        state, c_plus = sample_leading_term_cos(t_total - t_minus, state)
        eu, ev, ew = rotate_direction(u, v, w, c_minus, phi)
        state, n_stack = release(state, ELECTRON, t_minus, x, y, z, eu, ev, ew, cell, e_cut,
                                 wt, scheme, tally, ledger, counts, stack, n_stack)
        eu, ev, ew = rotate_direction(u, v, w, c_plus, phi + math.pi)
        state, n_stack = release(state, POSITRON, t_total - t_minus, x, y, z, eu, ev, ew, cell,
                                 e_cut, wt, scheme, tally, ledger, counts, stack, n_stack)
        return state, False, 0.0, u, v, w, n_stack
    state, cos_e = sample_sauter_cos(e, state)
    eu, ev, ew = rotate_direction(u, v, w, cos_e, phi)
    state, n_stack = release(state, ELECTRON, e, x, y, z, eu, ev, ew, cell, e_cut, wt, scheme,
                             tally, ledger, counts, stack, n_stack)
    return state, False, 0.0, u, v, w, n_stack


@kernel
def photon_track(wg, xs, ln_mu_hat, e, cell, x, y, z, u, v, w, state, kin, p_cut, e_cut, wt,
                 scheme, tally, ledger, counts, stack, n_stack):
    """Follow one photon of weight ``wt`` to its absorption, escape or cut-off; secondaries go on
    the stack; with ``scheme`` FOLLOW or REPEAT (XVMC's splitting) a photon of weight < 1 plays
    Russian roulette once it has scattered (survival wt, then weight 1); with REPEAT its first
    interaction draws from the stream ``kin`` shared by the copies (:mod:`._repeat`; later
    ones FOLLOW). Flights through the mesh are
    Woodcock-tracked with the majorant table ``ln_mu_hat``
    (:mod:`tetdose.transport.history._delta`), or walked tet by tet when it is empty.
    Returns (state, n_stack)."""
    delta = ln_mu_hat.shape[0] > 0
    while True:
        if e < p_cut:
            ledger[L_CUTOFF] += e * wt
            tally[cell] += e * wt
            return state, n_stack
        state, xi = next_uniform(state)
        if delta:
            state, out, cell2, x, y, z = flight_delta(wg, xs, ln_mu_hat, e, cell, x, y, z, u, v,
                                                      w, -math.log(1.0 - xi), state, tally,
                                                      counts)
        else:
            out, cell2, x, y, z = flight(wg, xs, e, cell, x, y, z, u, v, w,
                                         -math.log(1.0 - xi), False, tally, counts)
        if out == ESCAPES:
            ledger[L_ESCAPED] += e * wt
            return state, n_stack
        if out == LOST:
            ledger[L_LOST] += e * wt
            counts[C_LOST] += 1
            return state, n_stack
        cell = cell2
        if scheme == REPEAT:
            _, alive, e, u, v, w, n_stack = photon_interaction(
                xs, cell_material(wg, cell), cell, e, u, v, w, kin, e_cut, wt, scheme, tally,
                ledger, counts, stack, n_stack, x, y, z)
            scheme = FOLLOW
        else:
            state, alive, e, u, v, w, n_stack = photon_interaction(
                xs, cell_material(wg, cell), cell, e, u, v, w, state, e_cut, wt, scheme, tally,
                ledger, counts, stack, n_stack, x, y, z)
        if not alive:
            return state, n_stack
        if scheme != ROULETTE and wt < 1.0:
            state, xi = next_uniform(state)
            if xi >= wt:
                ledger[L_ROULETTE] += wt * e
                return state, n_stack
            ledger[L_ROULETTE] -= (1.0 - wt) * e
            wt = 1.0


@kernel
def wall_column(wg, cell, x, y, z):
    """A lower bound of the column density [mm·g/cm³] of any path from (x, y, z) to the walls of
    ``cell`` (module docstring); 0 for voxels listing mesh triangles."""
    m_tets = wg.tet.planes.shape[0]
    if cell < m_tets:
        g = wg.tet
        d = math.inf
        for f in range(4):
            d = min(d, g.planes[cell, f, 3] - (g.planes[cell, f, 0] * x + g.planes[cell, f, 1] * y
                                               + g.planes[cell, f, 2] * z))
        if d <= 0.0:
            return 0.0
        gx, gy, gz = g.density[cell, 0], g.density[cell, 1], g.density[cell, 2]
        rho_min = density_at(g, cell, x, y, z) - math.sqrt(gx * gx + gy * gy + gz * gz) * d
        return max(d * rho_min, 0.0)
    g = wg.vox
    vid = cell - m_tets
    if g.material[vid] < 0:
        return 0.0
    i, j, k = voxel_ijk(g, vid)
    ax = x - (g.lo[0] + i * g.cell[0])
    ay = y - (g.lo[1] + j * g.cell[1])
    az = z - (g.lo[2] + k * g.cell[2])
    d = min(ax, g.cell[0] - ax, ay, g.cell[1] - ay, az, g.cell[2] - az)
    return max(d, 0.0) * g.density[vid]


@kernel
def coupled_history(wg, xs, ln_mu_hat, et, sig_hat, sp, e, cell, x, y, z, u, v, w, state, kin,
                    p_cut, f_loss, wt, scheme, rr_mev, tally, ledger, counts, stack, bcell, bcol,
                    trk, key, dw):
    """Follow one source particle (species ``sp``, energy [MeV], already in global ``cell``,
    statistical weight ``wt``: 1, or 1/n_split for a split photon, whose electrons ``scheme``
    rouletted, followed with weight wt, or replayed from the track buffer ``trk``/``key``
    (:mod:`._repeat`; ``kin`` the copies' shared stream)) and every secondary to the end;
    electrons of at most ``rr_mev`` [MeV] are range-rejected (module docstring; 0: never);
    photons are Woodcock-tracked through the mesh with the majorant ``ln_mu_hat`` (empty: they
    walk it); ``dw`` the dose-to-water sums of the e± tracks
    (:class:`~tetdose.transport.history._electron.WaterTally`). Returns the RNG state."""
    n_stack = 0
    source = True
    while True:
        if sp == PHOTON:
            state, n_stack = photon_track(wg, xs, ln_mu_hat, e, cell, x, y, z, u, v, w, state,
                                          kin, p_cut, et.cutoff_mev, wt,
                                          scheme if source else min(scheme, FOLLOW), tally,
                                          ledger, counts, stack, n_stack)
        elif ((sp == ELECTRON or sp == REPLAY) and e <= rr_mev
              and range_of(et, cell_material(wg, cell), ELECTRON, e) * MM_PER_CM
              < wall_column(wg, cell, x, y, z)):
            tally[cell] += e * wt  # range rejection: the track cannot leave this voxel
            if dw.a.shape[0] > 0:
                water_end(dw, et, cell_material(wg, cell), ELECTRON, e, wt, cell)
            ledger[L_E_CUTOFF] += e * wt
            counts[C_E_TRACKS] += 1
        elif sp == REPLAY:
            state, n_stack = repeat_electron(wg, et, sig_hat, e, cell, x, y, z, u, v, w, wt,
                                             state, f_loss, tally, ledger, counts, stack, n_stack,
                                             bcell, bcol, trk, key, dw)
        else:
            state, n_stack = electron_track(wg, et, sig_hat, sp, e, cell, x, y, z, u, v, w, wt,
                                            state, f_loss, tally, ledger, counts, stack, n_stack,
                                            bcell, bcol, dw)
        if n_stack == 0:
            return state
        n_stack -= 1
        r = stack[n_stack]
        e, x, y, z, u, v, w = r[0], r[1], r[2], r[3], r[4], r[5], r[6]
        cell, sp, wt = int(r[7]), int(r[8]), r[9]
        source = False
