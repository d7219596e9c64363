"""njit photon histories on the tetrahedral mesh and on the voxel grid (same physics, same tallies).

Free path with a linear density. Inside tet k the density along the ray p + s·d is
``ρ(s) = ρ_p + a·s`` with ``a = ∇ρ_k · d``, so the optical depth to distance s [mm] is the quadratic

    τ(s) = (μ/ρ)(E) · (ρ_p·s + a·s²/2) / MM_PER_CM.

A sampled τ* = −ln(1 − ξ) is reached in this tet when ``C* = τ*·MM_PER_CM/(μ/ρ) < C(t_exit)``
(C = column density in mm·g/cm³); the distance is then the root of ``a s²/2 + ρ_p s − C* = 0``
taken in the cancellation-free form ``s = 2C* / (ρ_p + √(ρ_p² + 2aC*))`` — exact, no stepping.
Otherwise τ* −= τ(t_exit) and the photon moves to the neighbour. On voxels the density is
constant per voxel (a = 0) and the walk is Amanatides–Woo.

One world, one loop (:mod:`tetdose.transport.geometry._world`): a flight moves between the mesh
and the voxels any number of times, carrying the remaining optical depth τ across every switch
(τ is continuous; on the mesh it is held as column density and converted back on leaving).
Mesh-only and voxel-only runs are worlds with one part empty.

Tallies (energy per cell [MeV]): *analog* adds the energy the interaction leaves locally
(``interact``'s deposited energy: photo-electron, Compton electron, pair kinetic energy — i.e.
energy transferred, dose = collision kerma when electrons stop locally); *track_length* adds
``E·(μen/ρ)(E)·C/MM_PER_CM`` for every path segment of column density C (the kerma estimator,
analytic for a linear density). Photons below the energy cut-off, and secondaries beyond the
fixed stack, deposit locally in both modes. The energy ledger row is
``[source, deposited (analog), escaped, cut off, lost]`` in MeV and closes to round-off.
"""

import math

from numba import njit

from tetdose._constants import MM_PER_CM
from tetdose._jit import kernel
from tetdose._random import next_uniform
from tetdose.transport.geometry._tet import MAX_ZERO_STEPS, exit_face, next_tet, prefetch_neighbours
from tetdose.transport.geometry._voxel import dda_init, dda_step
from tetdose.transport.geometry._walk import (
    MAX_SWITCHES,
    after_grid,
    after_mesh,
    column_distance,
    relocated,
    tet_column,
    voxel_material,
    voxel_stretch_end,
)
from tetdose.transport.geometry._world import HIT_TOL_MM, cell_material, voxel_ijk
from tetdose.transport.physics._photon import interact, transport_coefficients

#: Ledger columns and counter columns.
L_SOURCE, L_DEPOSITED, L_ESCAPED, L_CUTOFF, L_LOST = 0, 1, 2, 3, 4
C_LOST, C_RELOCATIONS, C_STACK_FULL, C_CROSSINGS, C_VOXEL_STEPS, C_SWITCHES = 0, 1, 2, 3, 4, 5
C_MISSED = 6  # source photons whose ray meets neither the mesh nor the grid
N_LEDGER, N_COUNTS = 5, 7
#: Flight outcomes (ENTERS: a voxel flight reached the mesh).
INTERACTS, ESCAPES, LOST, ENTERS = 0, 1, 2, 3


@njit(cache=True, inline="always")
def flight_mesh(g, xs, e, k, entry, x, y, z, u, v, w, tau, track, tally, counts):
    """Move a photon through the mesh to its next interaction: (outcome, tet, x, y, z, τ).

    The remaining optical depth is carried as column density ``need = τ·MM_PER_CM/(μ/ρ)``
    [mm·g/cm³] (converted only when the material changes) and returned as τ when the photon
    leaves the mesh (ESCAPES, at its exit point). Tallies the track-length kerma along the way
    when ``track`` is true; adds the tets crossed to ``counts[C_CROSSINGS]``.
    """
    m_prev = -1
    mu = need = kerma = 0.0
    written = tally if track else tally[:0]  # tally cells written on crossings
    zero_steps = 0
    n_reloc = 0
    crossings = 0
    while True:
        m = g.material[k]
        if m != m_prev:
            if m_prev >= 0:
                tau = need * mu / MM_PER_CM
            mu, mu_en = transport_coefficients(xs, m, e)
            need = tau * MM_PER_CM / mu
            kerma = e * mu_en / MM_PER_CM
            m_prev = m
        prefetch_neighbours(g, k, entry, True, written)
        f, t = exit_face(g, k, x, y, z, u, v, w, entry)
        if f < 0 or zero_steps > MAX_ZERO_STEPS:
            counts[C_RELOCATIONS] += 1
            k, x, y, z, n_reloc = relocated(g, x, y, z, u, v, w, n_reloc)
            if k < 0:
                counts[C_CROSSINGS] += crossings
                return LOST, k, x, y, z, 0.0
            entry = -1
            zero_steps = 0
            continue
        rho0, a, col_exit = tet_column(g, k, x, y, z, u, v, w, t)
        if need < col_exit:
            s = column_distance(rho0, a, need, 0.0)
            if track:
                tally[k] += kerma * need
            counts[C_CROSSINGS] += crossings
            return INTERACTS, k, x + s * u, y + s * v, z + s * w, 0.0
        if track:
            tally[k] += kerma * col_exit
        need -= col_exit
        zero_steps = zero_steps + 1 if t == 0.0 else 0
        x, y, z = x + t * u, y + t * v, z + t * w
        nxt = g.link[k, f]
        k, entry = next_tet(g, k, f)
        crossings += 1
        if k < 0:  # the boundary: k = −1, or −2 if the face's plane supports the whole mesh
            counts[C_CROSSINGS] += crossings
            return ESCAPES, nxt, x, y, z, need * mu / MM_PER_CM


@njit(cache=True, inline="always")
def flight_voxel(wg, xs, e, vid, x, y, z, u, v, w, tau, t_min, track, tally, counts):
    """Move a photon through the voxels from (x, y, z) in voxel ``vid``: (outcome, cell, x, y, z, τ).

    Outcomes: INTERACTS (cell = global voxel cell ``M + vid``), ESCAPES (left the grid) or ENTERS
    (reached the mesh: cell = the tet entered, at the exact hit point, τ left). Entering hits at
    distances ≤ ``t_min`` [mm] are ignored (the caller's guard against zero-length ping-pong).
    """
    g = wg.vox
    off = wg.tet.planes.shape[0]
    nx, ny = g.n[0], g.n[1]
    i, j, k = voxel_ijk(g, vid)
    sx, sy, sz, tx, ty, tz, dx, dy, dz = dda_init(g, i, j, k, x, y, z, u, v, w)
    t_cur = 0.0
    m_prev = -1
    mu = mu_en = 0.0
    steps = 0
    while True:
        vid = (k * ny + j) * nx + i
        m, listed = voxel_material(g, vid)
        if m != m_prev:
            mu, mu_en = transport_coefficients(xs, m, e)
            m_prev = m
        b, t_end = voxel_stretch_end(wg, listed, i, j, k, x, y, z, u, v, w, t_cur, t_min,
                                     tx, ty, tz)
        col = g.density[vid] * max(t_end - t_cur, 0.0)
        need = tau * MM_PER_CM / mu
        if need < col:
            t_cur += need / g.density[vid]
            if track:
                tally[off + vid] += e * mu_en * need / MM_PER_CM
            counts[C_VOXEL_STEPS] += steps
            return INTERACTS, off + vid, x + t_cur * u, y + t_cur * v, z + t_cur * w, 0.0
        if track:
            tally[off + vid] += e * mu_en * col / MM_PER_CM
        tau -= mu * col / MM_PER_CM
        if b >= 0:
            counts[C_VOXEL_STEPS] += steps
            return ENTERS, wg.tet.bnd_tet[b], x + t_end * u, y + t_end * v, z + t_end * w, tau
        t_cur = max(t_end, t_cur)
        steps += 1
        i, j, k, tx, ty, tz, inside = dda_step(i, j, k, tx, ty, tz, sx, sy, sz, dx, dy, dz, g.n)
        if not inside:
            counts[C_VOXEL_STEPS] += steps
            return ESCAPES, -1, x + t_cur * u, y + t_cur * v, z + t_cur * w, tau


@njit(cache=True, inline="always")
def flight(wg, xs, e, cell, x, y, z, u, v, w, tau, track, tally, counts):
    """Move a photon from global ``cell`` to its next interaction through mesh and voxels:
    (outcome, cell, x, y, z). τ carries over every switch.

    Leaving the mesh, the photon continues in the voxel holding the exit point or, outside the
    grid, flies through vacuum to the next entering mesh face or the grid; leaving the grid, to
    a mesh part beyond it, if any (:func:`~._geometry_world.vacuum_flight`). A zero-length
    visit (entered and left at the same point) makes the next re-entry ignore hits closer than
    :data:`HIT_TOL_MM`, so rounding at an edge cannot ping-pong.
    """
    m_tets = wg.tet.planes.shape[0]
    t_min = -HIT_TOL_MM
    for _ in range(MAX_SWITCHES):
        if cell < m_tets:
            x0, y0, z0 = x, y, z
            out, k, x, y, z, tau = flight_mesh(wg.tet, xs, e, cell, -1, x, y, z, u, v, w, tau,
                                               track, tally, counts)
            if out != ESCAPES:
                return out, k, x, y, z
            cell, x, y, z, t_min = after_mesh(wg, k, x0, y0, z0, x, y, z, u, v, w)
        else:
            out, cell, x, y, z, tau = flight_voxel(wg, xs, e, cell - m_tets, x, y, z, u, v, w,
                                                   tau, t_min, track, tally, counts)
            if out == INTERACTS:
                return out, cell, x, y, z
            t_min = -HIT_TOL_MM
            if out == ESCAPES:  # left the grid: vacuum, maybe a mesh part beyond the CT
                cell, x, y, z = after_grid(wg, x, y, z, u, v, w)
        if cell < 0:
            return ESCAPES, -1, x, y, z
        counts[C_SWITCHES] += 1
    return LOST, cell, x, y, z


@kernel
def interaction(xs, m, cell, e, u, v, w, state, cutoff, track, tally, ledger, counts,
                stack, n_stack, x, y, z):
    """Sample the interaction at (x, y, z) in ``cell``; push a secondary; book the energy.

    Returns (state, alive, e, u, v, w, n_stack) of the continuing photon.
    """
    state, _proc, dep, e_out, u2, v2, w2, e_sec, su, sv, sw = interact(xs, m, e, u, v, w, state)
    ledger[L_DEPOSITED] += dep
    if not track:
        tally[cell] += dep
    if e_sec > 0.0:
        if e_sec >= cutoff and n_stack < stack.shape[0]:
            stack[n_stack, 0] = e_sec
            stack[n_stack, 1], stack[n_stack, 2], stack[n_stack, 3] = x, y, z
            stack[n_stack, 4], stack[n_stack, 5], stack[n_stack, 6] = su, sv, sw
            stack[n_stack, 7] = cell
            n_stack += 1
        else:
            if e_sec >= cutoff:
                counts[C_STACK_FULL] += 1
            ledger[L_CUTOFF] += e_sec
            tally[cell] += e_sec
    if e_out < cutoff:
        ledger[L_CUTOFF] += e_out
        tally[cell] += e_out
        return state, False, e_out, u2, v2, w2, n_stack
    return state, True, e_out, u2, v2, w2, n_stack


@njit(cache=True, inline="always")
def pop_photon(stack, i):
    """Row ``i`` of the secondary stack, as pushed by :func:`interaction`:
    (energy [MeV], x, y, z [mm], u, v, w, cell id)."""
    r = stack[i]
    return r[0], r[1], r[2], r[3], r[4], r[5], r[6], int(r[7])


@kernel
def history(wg, xs, e, cell, x, y, z, u, v, w, state, cutoff, track, tally, ledger, counts,
            stack):
    """Follow one source photon (already in global ``cell``) and its secondaries to the end."""
    n_stack = 0
    while True:
        state, xi = next_uniform(state)
        out, cell2, x, y, z = flight(wg, xs, e, cell, x, y, z, u, v, w, -math.log(1.0 - xi),
                                     track, tally, counts)
        alive = False
        if out == ESCAPES:
            ledger[L_ESCAPED] += e
        elif out == LOST:
            ledger[L_LOST] += e
            counts[C_LOST] += 1
        else:
            cell = cell2
            state, alive, e, u, v, w, n_stack = interaction(
                xs, cell_material(wg, cell), cell, e, u, v, w, state, cutoff, track, tally,
                ledger, counts, stack, n_stack, x, y, z)
        if not alive:
            if n_stack == 0:
                return state
            n_stack -= 1
            e, x, y, z, u, v, w, cell = pop_photon(stack, n_stack)
