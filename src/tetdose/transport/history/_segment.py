"""njit straight segments of a given column density through the world (electron steps).

An electron step is a mass thickness s [g/cm²]; a segment of it is a straight move until the
column density ``C = ∫ρ dl`` [mm·g/cm³] (= s·MM_PER_CM) is used up. Inside tet k the density
along p + l·d is ρ_p + a·l (a = ∇ρ_k·d), so the column to the exit face at l = t is
ρ_p·t + a·t²/2, and a column C* < C(t) is reached at the root
``l = 2C*/(ρ_p + √(ρ_p² + 2aC*))`` — exact for the linear density, no sub-stepping (the same
algebra as the photon free path, :mod:`tetdose.transport.history._photon`). In a voxel the
density is constant. The walk crosses tets (face to face), voxels (Amanatides–Woo), switches
between mesh and voxels at the exact hit points as photons do, and crosses vacuum (outside the
mesh and the grid: no mass, so the column does not change) to the next entry; it stops early

- at a cell of another material (``SEG_MATERIAL``: the point on the interface, the new cell);
- when the buffer of crossed cells is full (``SEG_FULL``, at a cell boundary);
- when nothing lies ahead (``SEG_ESCAPED``) or the walk is lost (``SEG_LOST``).

Every cell crossed with a positive column is appended to ``(bcell, bcol)`` with that column
(consecutive entries of one cell merged), so the caller can share the step's energy loss in
proportion to the mass thickness in each cell. The buffer always keeps two free entries.
"""

from numba import njit

from tetdose._jit import kernel
from tetdose.transport.geometry._tet import MAX_ZERO_STEPS, density_at, exit_face, next_tet
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
from tetdose.transport.history._photon import (
    C_CROSSINGS,
    C_RELOCATIONS,
    C_SWITCHES,
    C_VOXEL_STEPS,
)

#: Segment outcomes.
SEG_DONE, SEG_MATERIAL, SEG_FULL, SEG_ESCAPED, SEG_LOST = 0, 1, 2, 3, 4
#: Internal outcomes of the mesh and voxel parts.
_LEFT, _ENTERS = 5, 6


@kernel
def _append(bcell, bcol, nb, cell, col):
    """Add column ``col`` of ``cell`` to the buffer (merged with the last entry if the same)."""
    if col <= 0.0:
        return nb
    if nb > 0 and bcell[nb - 1] == cell:
        bcol[nb - 1] += col
        return nb
    bcell[nb] = cell
    bcol[nb] = col
    return nb + 1


@kernel
def segment_mesh(g, k, entry, x, y, z, u, v, w, need, mat, bcell, bcol, nb, counts):
    """Walk the mesh from tet ``k`` (entered through face ``entry``, −1 if unknown) until the
    column ``need`` [mm·g/cm³] is used up: (outcome, cell, entry, x, y, z, need left, nb).

    Outcomes: SEG_DONE (cell = the tet it ends in), SEG_MATERIAL / SEG_FULL (cell, entry = the
    next tet and its entry face), _LEFT (left the mesh: cell = the face's link, −1 or
    SUPPORTING), SEG_LOST.
    """
    zero_steps = 0
    n_reloc = 0
    crossings = 0
    while True:
        f, t = exit_face(g, k, x, y, z, u, v, w, entry)
        if f < 0 or zero_steps > MAX_ZERO_STEPS:
            counts[C_RELOCATIONS] += 1
            k, x, y, z, n_reloc = relocated(g, x, y, z, u, v, w, n_reloc)
            if k < 0:
                counts[C_CROSSINGS] += crossings
                return SEG_LOST, k, -1, x, y, z, need, nb
            entry = -1
            zero_steps = 0
            if g.material[k] != mat:
                counts[C_CROSSINGS] += crossings
                return SEG_MATERIAL, k, -1, x, y, z, need, nb
            continue
        rho0, a, col_exit = tet_column(g, k, x, y, z, u, v, w, t)
        col_exit = max(col_exit, 0.0)
        if need < col_exit:
            s = min(column_distance(rho0, a, need, t), t)
            nb = _append(bcell, bcol, nb, k, need)
            counts[C_CROSSINGS] += crossings
            return SEG_DONE, k, entry, x + s * u, y + s * v, z + s * w, 0.0, nb
        nb = _append(bcell, bcol, nb, k, col_exit)
        need -= col_exit
        zero_steps = zero_steps + 1 if t == 0.0 else 0
        x, y, z = x + t * u, y + t * v, z + t * w
        nxt = g.link[k, f]
        k, entry = next_tet(g, k, f)
        crossings += 1
        out = -1
        if k < 0:
            out, k = _LEFT, nxt
        elif g.material[k] != mat:
            out = SEG_MATERIAL
        elif nb >= bcell.shape[0] - 2:
            out = SEG_FULL
        if out >= 0:
            counts[C_CROSSINGS] += crossings
            return out, k, entry, x, y, z, need, nb


@kernel
def segment_voxel(wg, vid, x, y, z, u, v, w, need, mat, t_min, bcell, bcol, nb, counts):
    """Walk the voxels from voxel ``vid``: (outcome, cell, x, y, z, need left, nb).

    Outcomes: SEG_DONE, SEG_MATERIAL, SEG_FULL (cell = the global voxel cell), _ENTERS (reached
    the mesh: cell = the tet entered at the exact hit point), _LEFT (left the grid). Entering
    hits at distances ≤ ``t_min`` [mm] are ignored (the photon flight's guard).
    """
    g = wg.vox
    off = wg.tet.planes.shape[0]
    nx, ny = g.n[0], g.n[1]
    i, j, k = voxel_ijk(g, vid)
    sx, sy, sz, tx, ty, tz, dx, dy, dz = dda_init(g, i, j, k, x, y, z, u, v, w)
    t_cur = 0.0
    steps = 0
    while True:
        vid = (k * ny + j) * nx + i
        m, listed = voxel_material(g, vid)
        out = -1
        if steps > 0 and m != mat:
            out = SEG_MATERIAL
        elif steps > 0 and nb >= bcell.shape[0] - 2:
            out = SEG_FULL
        if out >= 0:
            counts[C_VOXEL_STEPS] += steps
            return out, off + vid, x + t_cur * u, y + t_cur * v, z + t_cur * w, need, nb
        b, t_end = voxel_stretch_end(wg, listed, i, j, k, x, y, z, u, v, w, t_cur, t_min,
                                     tx, ty, tz)
        rho = g.density[vid]
        col = rho * max(t_end - t_cur, 0.0)
        if need < col:
            t_cur += need / rho
            nb = _append(bcell, bcol, nb, off + vid, need)
            counts[C_VOXEL_STEPS] += steps
            return SEG_DONE, off + vid, x + t_cur * u, y + t_cur * v, z + t_cur * w, 0.0, nb
        nb = _append(bcell, bcol, nb, off + vid, col)
        need -= col
        if b >= 0:
            counts[C_VOXEL_STEPS] += steps
            return (_ENTERS, wg.tet.bnd_tet[b], x + t_end * u, y + t_end * v, z + t_end * w,
                    need, nb)
        t_cur = max(t_end, t_cur)
        steps += 1
        i, j, k, tx, ty, tz, inside = dda_step(i, j, k, tx, ty, tz, sx, sy, sz, dx, dy, dz, g.n)
        if not inside:
            counts[C_VOXEL_STEPS] += steps
            return _LEFT, -1, x + t_cur * u, y + t_cur * v, z + t_cur * w, need, nb


@njit(cache=True, inline="always")
def within_cell(wg, cell, x, y, z, u, v, w, col):
    """Length [mm] of a straight move of column ``col`` [mm·g/cm³] from (x, y, z) in global
    ``cell`` if the cell holds its end strictly inside — a tet or a box is convex, so it holds
    the whole move then — else −1. In a tet the length is the exact root of the linear density
    (:func:`~tetdose.transport.geometry._walk.column_distance`); voxels that list mesh
    triangles are left to the walk."""
    m_tets = wg.tet.planes.shape[0]
    if cell < m_tets:
        g = wg.tet
        rho0 = density_at(g, cell, x, y, z)
        if not rho0 > 0.0:
            return -1.0
        a = g.density[cell, 0] * u + g.density[cell, 1] * v + g.density[cell, 2] * w
        s = column_distance(rho0, a, col, -1.0)
        ex, ey, ez = x + s * u, y + s * v, z + s * w
        for f in range(4):
            if (g.planes[cell, f, 0] * ex + g.planes[cell, f, 1] * ey + g.planes[cell, f, 2] * ez
                    >= g.planes[cell, f, 3]):
                return -1.0
        return s
    g = wg.vox
    vid = cell - m_tets
    if g.material[vid] < 0 or g.density[vid] <= 0.0:
        return -1.0
    s = col / g.density[vid]
    i, j, k = voxel_ijk(g, vid)
    bx, by, bz = g.lo[0] + i * g.cell[0], g.lo[1] + j * g.cell[1], g.lo[2] + k * g.cell[2]
    ex, ey, ez = x + s * u, y + s * v, z + s * w
    if (bx < ex < bx + g.cell[0] and by < ey < by + g.cell[1] and bz < ez < bz + g.cell[2]):
        return s
    return -1.0


@njit(cache=True, inline="always")
def segment(wg, cell, entry, x, y, z, u, v, w, need, mat, bcell, bcol, nb, counts):
    """Move a straight segment of column ``need`` [mm·g/cm³] from global ``cell`` through the
    world (module docstring): (outcome, cell, entry, x, y, z, need left, nb).

    The mesh ↔ voxel switches and vacuum gaps follow the photon flight
    (:func:`tetdose.transport.history._photon.flight`); a cell reached across a switch or a gap
    that holds another material ends the segment there (SEG_MATERIAL). A move that ends in
    the tet or voxel it starts in (:func:`within_cell`) skips the walk.
    """
    s = within_cell(wg, cell, x, y, z, u, v, w, need)
    if s >= 0.0:  # the common short move inside one cell
        nb = _append(bcell, bcol, nb, cell, need)
        return (SEG_DONE, cell, entry if cell < wg.tet.planes.shape[0] else -1, x + s * u,
                y + s * v, z + s * w, 0.0, nb)
    m_tets = wg.tet.planes.shape[0]
    t_min = -HIT_TOL_MM
    for _ in range(MAX_SWITCHES):
        if cell < m_tets:
            x0, y0, z0 = x, y, z
            out, k, entry, x, y, z, need, nb = segment_mesh(
                wg.tet, cell, entry, x, y, z, u, v, w, need, mat, bcell, bcol, nb, counts)
            if out != _LEFT:
                return out, k, entry, x, y, z, need, nb
            cell, x, y, z, t_min = after_mesh(wg, k, x0, y0, z0, x, y, z, u, v, w)
        else:
            out, cell, x, y, z, need, nb = segment_voxel(
                wg, cell - m_tets, x, y, z, u, v, w, need, mat, t_min, bcell, bcol, nb, counts)
            if out != _LEFT and out != _ENTERS:
                return out, cell, -1, x, y, z, need, nb
            t_min = -HIT_TOL_MM
            if out == _LEFT:
                cell, x, y, z = after_grid(wg, x, y, z, u, v, w)
        entry = -1
        if cell < 0:
            return SEG_ESCAPED, -1, -1, x, y, z, need, nb
        counts[C_SWITCHES] += 1
        if cell_material(wg, cell) != mat:
            return SEG_MATERIAL, cell, -1, x, y, z, need, nb
    return SEG_LOST, cell, -1, x, y, z, need, nb
