"""njit Woodcock (delta) tracking of photons through the mesh (or a voxel-only grid) in dose mode.

**Method** (Woodcock, Murphy, Hemmings & Longworth, ANL-7050, 1965; for unstructured geometry
Leppänen, Ann. Nucl. Energy 37:715, 2010). Inside the mesh's point-location box B (its
bounding box, :func:`tetdose.transport.geometry.tets.location_grid`) the photon flies with a
majorant μ̂(E) ≥ μ(x, E) for every x in B: a tentative distance s = −ln(1 − ξ)/μ̂, a move, then
the point's cell by point location (:func:`~tetdose.transport.geometry._tet.locate_point`) and
the real attenuation μ(x) = (μ/ρ)_m(E)·ρ(x) there, with the exact linear density of the tet
(:func:`~tetdose.transport.geometry._tet.density_at`); the collision is real with probability
μ(x)/μ̂, else fictitious and the flight goes on. The real collisions are those of the analog
process (free paths distributed as exp(−∫μ ds)) whatever μ̂ ≥ μ: no walk, no column integral,
no face test, only one point location per tentative collision.

Inside B but outside the mesh the point is in the voxel that holds it (a hybrid world: the
mesh is the only truth inside it, the voxels outside it, as in
:mod:`tetdose.transport.geometry._world`) or in vacuum (μ = 0: always fictitious). So the
majorant covers those voxels too: ``ln_mu_hat[i] = max_m (ln (μ/ρ)_m(E_i) + ln ρ_max,m)`` on
the cross sections' nodes, ρ_max,m the largest density of material m over the mesh's vertices
(a linear density peaks at a vertex) and the voxels meeting B
(:attr:`~tetdose.transport.geometry._tet.TetGeometry.rho_max`). Its interpolation linear in
ln E bounds every material's (a maximum of node values bounds each interpolant), so μ̂ ≥ μ
exactly, not only at the nodes (:func:`tetdose.transport.run.coupled.photon_majorant`).

**Boundary.** The flight leaves B when the next tentative distance lies beyond B's far face:
it moves to the exit point (outside the mesh) with the unused optical depth μ̂·(s − t_B), an
Exp(1) variable by the memoryless exponential, and continues exactly as the walking flight of
:func:`tetdose.transport.history._photon.flight` does on leaving the mesh: in the voxel there,
or through vacuum to the grid. A voxel flight that reaches the mesh (its triangle lists) hands
the photon back to Woodcock tracking at the hit point with the optical depth left. B is convex
and holds the mesh, so a photon that left B never meets the mesh again along that line.

**Voxel-only worlds** (no mesh) use the same flight with the grid as the box B and the voxel
holding each tentative point as its cell: ``ρ_max,m`` is then the largest density of material m
over the voxels (a water phantom: μ̂ = μ, every tentative collision is real, one step per
flight instead of a voxel walk; a CT: the densest material bounds the rest). Leaving the grid,
the photon escapes (nothing lies beyond it).

Electrons keep walking the tets (they need the mass thickness along their path); kerma mode
keeps the walking flight (its track-length estimator needs every segment).
"""

import math

from numba import njit

from tetdose._constants import MM_PER_CM
from tetdose._random import next_uniform
from tetdose.transport.geometry._tet import density_at, locate_point
from tetdose.transport.geometry._voxel import box_interval
from tetdose.transport.geometry._walk import MAX_SWITCHES, after_grid
from tetdose.transport.geometry._world import (
    HIT_TOL_MM,
    cell_material,
    vacuum_flight,
    voxel_cell_at,
)
from tetdose.transport.history._electron import C_DELTA_STEPS
from tetdose.transport.history._photon import (
    C_SWITCHES,
    ESCAPES,
    INTERACTS,
    LOST,
    flight_voxel,
)
from tetdose.transport.physics._photon import grid_position, majorant_at, mu_transported_at


@njit(cache=True, inline="always")
def woodcock_box(wg, xs, ln_mu_hat, e, x, y, z, u, v, w, tau, state, counts):
    """Woodcock flight from (x, y, z) in the point-location box: (state, outcome, cell, x, y,
    z, τ).

    INTERACTS: a real collision in ``cell`` (a tet, or a voxel outside the mesh) at (x, y, z).
    ESCAPES: the photon left the box at (x, y, z) with optical depth τ left. The first
    tentative distance uses the given ``tau``, later ones fresh numbers of ``state``; counts the
    tentative collisions in ``counts[C_DELTA_STEPS]``.
    """
    g = wg.tet
    m_tets = g.planes.shape[0]
    has_voxels = wg.vox.density.shape[0] > 0
    if m_tets > 0:
        _, t_box = box_interval(g.loc_lo, g.loc_cell, g.loc_n, x, y, z, u, v, w)
    else:  # a voxel-only world: the box is the grid
        _, t_box = box_interval(wg.vox.lo, wg.vox.cell, wg.vox.n, x, y, z, u, v, w)
    t_box = max(t_box, 0.0)
    i, f = grid_position(xs, e)
    mu_hat = majorant_at(ln_mu_hat, i, f)  # [1/cm]
    m_prev = -1
    mu_rho = 0.0
    t = 0.0
    steps = 0
    while True:
        if tau * MM_PER_CM >= mu_hat * (t_box - t):  # the next tentative collision is beyond B
            tau -= mu_hat * (t_box - t) / MM_PER_CM
            counts[C_DELTA_STEPS] += steps
            return state, ESCAPES, -1, x + t_box * u, y + t_box * v, z + t_box * w, tau
        t += tau * MM_PER_CM / mu_hat
        steps += 1
        px, py, pz = x + t * u, y + t * v, z + t * w
        cell = locate_point(g, px, py, pz) if m_tets > 0 else -1
        rho = 0.0
        if cell >= 0:
            rho = max(density_at(g, cell, px, py, pz), 0.0)
        elif has_voxels:
            cell = voxel_cell_at(wg, px, py, pz)
            if cell >= 0:
                rho = wg.vox.density[cell - m_tets]
        if rho > 0.0:
            m = cell_material(wg, cell)
            if m != m_prev:
                mu_rho = mu_transported_at(xs, m, i, f)
                m_prev = m
            state, xi = next_uniform(state)
            if xi * mu_hat < mu_rho * rho:  # real with probability μ(x)/μ̂
                counts[C_DELTA_STEPS] += steps
                return state, INTERACTS, cell, px, py, pz, 0.0
        state, xi = next_uniform(state)
        tau = -math.log(1.0 - xi)


@njit(cache=True, inline="always")
def flight_delta(wg, xs, ln_mu_hat, e, cell, x, y, z, u, v, w, tau, state, tally, counts):
    """Move a photon from global ``cell`` to its next real interaction: (state, outcome, cell,
    x, y, z), as :func:`~tetdose.transport.history._photon.flight` (dose mode: no track-length
    tally) but by Woodcock tracking wherever the photon is in the mesh (module docstring).
    τ carries over every switch."""
    m_tets = wg.tet.planes.shape[0]
    has_voxels = wg.vox.density.shape[0] > 0
    for _ in range(MAX_SWITCHES):
        if cell < m_tets or m_tets == 0:
            state, out, cell, x, y, z, tau = woodcock_box(wg, xs, ln_mu_hat, e, x, y, z, u, v,
                                                          w, tau, state, counts)
            if out == INTERACTS or m_tets == 0:
                return state, out, cell, x, y, z
            cell = voxel_cell_at(wg, x, y, z) if has_voxels else -1
            if cell < 0 and has_voxels:  # outside the grid: vacuum until it, if it lies ahead
                cell, x, y, z = vacuum_flight(wg, x, y, z, u, v, w, 0.0)
        else:
            out, cell, x, y, z, tau = flight_voxel(wg, xs, e, cell - m_tets, x, y, z, u, v, w,
                                                   tau, -HIT_TOL_MM, False, tally, counts)
            if out == INTERACTS:
                return state, out, cell, x, y, z
            if out == ESCAPES:  # left the grid: vacuum, maybe a mesh part beyond the CT
                cell, x, y, z = after_grid(wg, x, y, z, u, v, w)
            # ENTERS: cell is the tet entered, Woodcock tracking from the hit point
        if cell < 0:
            return state, ESCAPES, -1, x, y, z
        counts[C_SWITCHES] += 1
    return state, LOST, cell, x, y, z
