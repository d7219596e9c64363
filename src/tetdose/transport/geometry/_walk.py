"""njit steps shared by every straight walk through the world: photon flights
(:mod:`tetdose.transport.history._photon`) and electron segments
(:mod:`tetdose.transport.history._segment`).

- In tet k the density along p + l·d is ρ_p + a·l (a = ∇ρ_k·d), so the column density to the
  exit face at l = t is C(t) = ρ_p·t + a·t²/2 [mm·g/cm³] (:func:`tet_column`) and a column
  C* < C(t) is reached at l = 2C*/(ρ_p + √(ρ_p² + 2aC*)), the cancellation-free root
  (:func:`column_distance`) — exact for the linear density.
- A tet whose exit cannot be found (rounding at an edge, or stuck at one point) is left by a
  relocation a nudge ahead (:func:`relocated`).
- A voxel stretch ends at the voxel's wall or, in a voxel that lists mesh triangles, at the first
  entering hit (:func:`voxel_material`, :func:`voxel_stretch_end`).
- Leaving the mesh, a walk continues in the voxel holding the exit point or flies through vacuum
  to the next entry (:func:`after_mesh`); leaving the grid, to a mesh part beyond it
  (:func:`after_grid`).
"""

import math

from numba import njit

from tetdose.transport.geometry._tet import SUPPORTING, density_at, relocate
from tetdose.transport.geometry._world import (
    HIT_TOL_MM,
    mesh_hit_in_voxel,
    vacuum_flight,
    voxel_cell_at,
)

#: Nudge along the ray before a relocation [mm], and relocations allowed per flight.
RELOCATE_NUDGE_MM = 1e-6
MAX_RELOCATIONS = 4
#: Mesh ↔ voxel switches allowed in one flight before the particle is counted lost.
MAX_SWITCHES = 10_000


@njit(cache=True, inline="always")
def tet_column(g, k, x, y, z, u, v, w, t):
    """(ρ_p [g/cm³] at (x, y, z), a = ∇ρ_k·d [g/cm³/mm], column C(t) [mm·g/cm³]) in tet k."""
    rho0 = max(density_at(g, k, x, y, z), 0.0)
    a = g.density[k, 0] * u + g.density[k, 1] * v + g.density[k, 2] * w
    return rho0, a, rho0 * t + 0.5 * a * t * t


@njit(cache=True, inline="always")
def column_distance(rho0, a, need, fallback):
    """Distance [mm] at which the column ``need`` [mm·g/cm³] is reached from density ρ_p with
    slope a (module docstring); ``fallback`` where ρ_p + √(…) vanishes (no mass ahead)."""
    den = rho0 + math.sqrt(max(rho0 * rho0 + 2.0 * a * need, 0.0))
    return 2.0 * need / den if den > 0.0 else fallback


@njit(cache=True, inline="always")
def relocated(g, x, y, z, u, v, w, n_reloc):
    """The tet a nudge ahead of (x, y, z) after a failed exit: (k, x, y, z, n_reloc + 1), the
    point moved by the nudge; k = −1 when lost (outside, or more than MAX_RELOCATIONS)."""
    n_reloc += 1
    k = relocate(g, x, y, z, u, v, w, RELOCATE_NUDGE_MM)
    if k < 0 or n_reloc > MAX_RELOCATIONS:
        return -1, x, y, z, n_reloc
    nudge = RELOCATE_NUDGE_MM
    return k, x + nudge * u, y + nudge * v, z + nudge * w, n_reloc


@njit(cache=True, inline="always")
def voxel_material(g, vid):
    """(material index, lists mesh triangles) of voxel ``vid`` (listed: stored as −m − 1)."""
    m = g.material[vid]
    if m < 0:
        return -m - 1, True
    return m, False


@njit(cache=True, inline="always")
def voxel_stretch_end(wg, listed, i, j, k, x, y, z, u, v, w, t_cur, t_min, tx, ty, tz):
    """(b, t_end): where the walk from distance t_cur [mm] leaves voxel (i, j, k) — its wall, or
    the first entering hit on listed mesh triangle b (≥ 0) beyond ``t_min``."""
    t_end = min(tx, ty, tz)
    b = -1
    if listed:
        b, t_hit = mesh_hit_in_voxel(wg, i, j, k, x, y, z, u, v, w,
                                     max(t_cur - HIT_TOL_MM, t_min), t_end)
        if b >= 0:
            t_end = max(t_hit, t_cur)
    return b, t_end


@njit(cache=True, inline="always")
def after_mesh(wg, k, x0, y0, z0, x, y, z, u, v, w):
    """Where a walk goes on after leaving the mesh at (x, y, z) through a face whose link is
    ``k`` (SUPPORTING: its plane holds the whole mesh), having entered it at (x0, y0, z0):
    (cell, x, y, z, t_min) — the voxel there or, across vacuum, the next entry (−1: none).
    A zero-length visit makes the next re-entry ignore hits closer than HIT_TOL_MM (``t_min``)."""
    has_vox = wg.vox.density.shape[0] > 0
    t_min = HIT_TOL_MM if (x == x0 and y == y0 and z == z0) else -HIT_TOL_MM
    cell = voxel_cell_at(wg, x, y, z) if has_vox else -1
    if cell < 0 and (k != SUPPORTING or has_vox):
        cell, x, y, z = vacuum_flight(wg, x, y, z, u, v, w, max(t_min, 0.0))
    return cell, x, y, z, t_min


@njit(cache=True, inline="always")
def after_grid(wg, x, y, z, u, v, w):
    """Where a walk goes on after leaving the grid: a mesh part beyond it across vacuum, or −1."""
    if wg.tet.planes.shape[0] > 0:
        return vacuum_flight(wg, x, y, z, u, v, w, 0.0)
    return -1, x, y, z
