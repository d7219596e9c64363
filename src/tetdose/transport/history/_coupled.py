"""njit coupled photon–electron histories (dose mode): photons set electrons in motion.

Photon flights through the mesh are Woodcock (delta) tracked by default (a majorant, point
location, no tet walk: :mod:`tetdose.transport.history._delta`); with
``photon_tracking="walk"`` they are those of kerma mode
(:func:`tetdose.transport.history._photon.flight`, exact free paths in linear density, no
track-length tally). Both are exact. Each interaction's charged particles are transported
(:mod:`tetdose.transport.history._interaction`).

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
they are born (no roulette: it would add variance and save nothing). Every particle an electron
creates (δ-rays, bremsstrahlung, annihilation) has weight 1, so electron tracks never carry a
weight. The roulette's energy balance is the ledger column L_ROULETTE (+ w·E for a killed
particle, − (1 − w)·E for a survivor), so deposited + escaped + cut off + lost + roulette =
source exactly in every history, and the roulette column averages to zero.

**XVMC's splitting** (``splitting_scheme="follow"``; Kawrakow & Fippel, PMB 45:2163, 2000,
sec. 2.3): the copies of weight w = 1/n_split are made the same way, but every electron or
positron a copy sets in motion is followed with weight w (not rouletted), its deposits and
δ-rays weighted w; the photons of weight w < 1 that scatter, and every photon a weighted
electron creates (bremsstrahlung, annihilation), play Russian roulette instead: survival w,
then weight 1, so photons never carry a weight for long and the photon shower stays as cheap
as without splitting (:mod:`tetdose.transport.history._electron`). Ledger as above. Alone it
multiplies the electrons by n_split (gain ≈ 1: measured, bench/bench_vr.py).

**XVMC's splitting along the ray with history repetition** (``"repeat"``): every photon of
weight 1 — source photon, survivor of the roulette, photon an unweighted electron creates — is
split into n_split copies whose interaction sites are evenly spaced along its ray and found in one
walk; the copies share their interaction, and their electrons one track, replayed from each site
(:mod:`tetdose.transport.history._split`, :mod:`tetdose.transport.history._repeat`).

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
    L_E_CUTOFF,
    PHOTON,
    REPLAY,
    electron_track,
    roulette_survives,
    water_end,
)
from tetdose.transport.history._interaction import REPEAT, ROULETTE, photon_interaction
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
from tetdose.transport.history._split import split_photon
from tetdose.transport.physics._electron import range_of


@kernel
def photon_track(wg, xs, ln_mu_hat, e, cell, x, y, z, u, v, w, state, p_cut, e_cut, wt, scheme,
                 n_split, qs, sites, tally, ledger, counts, stack, n_stack):
    """Follow one photon of weight ``wt`` to its absorption, escape or cut-off; secondaries go on
    the stack. With ``scheme`` FOLLOW or REPEAT (XVMC's splitting) a photon of weight < 1 plays
    Russian roulette once it has scattered (survival wt, then weight 1); with REPEAT a photon of
    weight 1 is split into ``n_split`` copies along its ray instead (:mod:`._split`; ``sites``
    its buffer). Flights through the mesh are Woodcock-tracked with the majorant table
    ``ln_mu_hat`` (:mod:`tetdose.transport.history._delta`), or walked tet by tet when it is
    empty. Returns (state, n_stack)."""
    delta = ln_mu_hat.shape[0] > 0
    while True:
        if e < p_cut:
            ledger[L_CUTOFF] += e * wt
            tally[cell] += e * wt
            return state, n_stack
        if scheme == REPEAT and wt == 1.0 and n_split > 1:
            return split_photon(wg, xs, e, cell, x, y, z, u, v, w, state, n_split, qs, e_cut,
                                sites, tally, ledger, counts, stack, n_stack)
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
        state, alive, e, u, v, w, n_stack = photon_interaction(
            xs, cell_material(wg, cell), cell, e, u, v, w, state, e_cut, wt, scheme, tally,
            ledger, counts, stack, n_stack, x, y, z)
        if not alive:
            return state, n_stack
        if scheme != ROULETTE and wt < 1.0:
            state, survives = roulette_survives(state, wt, e, ledger)
            if not survives:
                return state, n_stack
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
def coupled_history(wg, xs, ln_mu_hat, et, sig_hat, sp, e, cell, x, y, z, u, v, w, state, p_cut,
                    f_loss, wt, scheme, n_split, n_split2, rr_mev, qs, tally, ledger, counts,
                    stack, bcell, bcol, sites, trk, key, dw):
    """Follow one source particle (species ``sp``, energy [MeV], already in global ``cell``,
    statistical weight ``wt``: 1, or 1/n_split for a copy of a split photon, whose electrons
    ``scheme`` rouletted or followed with weight wt; with REPEAT every photon of weight 1 is
    split along its ray, the source photon into ``n_split`` copies and every later one into
    ``n_split2`` ≤ n_split (``sites`` their buffer), and their electrons are
    replayed from the track buffer ``trk``/``key`` (:mod:`._split`, :mod:`._repeat`)) and every
    secondary to the end;
    electrons of at most ``rr_mev`` [MeV] are range-rejected (module docstring; 0: never);
    photons are Woodcock-tracked through the mesh with the majorant ``ln_mu_hat`` (empty: they
    walk it); ``dw`` the dose-to-water sums of the e± tracks
    (:class:`~tetdose.transport.history._electron.WaterTally`). Returns the RNG state."""
    n_stack = 0
    n_now = n_split if sp == PHOTON else n_split2  # the source photon's copies, or a later one's
    while True:
        if sp == PHOTON:
            state, n_stack = photon_track(wg, xs, ln_mu_hat, e, cell, x, y, z, u, v, w, state,
                                          p_cut, et.cutoff_mev, wt, scheme, n_now, qs, sites,
                                          tally, ledger, counts, stack, n_stack)
            n_now, qs = n_split2, (-1.0, -1.0, -1.0)
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
