"""njit source sampling: one source photon's (energy, position, direction) from flat beam arrays.

Source sampling: beam b is chosen with probability w_b/Σw (cumulative ``beam_cdf``), its energy
from the discrete lines of its spectrum (cumulative ``spec_cdf``). Pencil: fixed point and
direction. Parallel: uniform on the rectangle ``pos + (ξ₁−½)·fx·e1 + (ξ₂−½)·fy·e2``. Point: cone
about the axis, cos θ uniform on [cos θ_half, 1], φ uniform (isotropic for θ_half = 180°).
Linac: a point source at ``pos``; a rectangle r of the beam's aperture is chosen with probability
area_r/Σarea (cumulative ``rect_cdf``), a point (a₁, a₂) uniform in it on the isocentre plane, and
the photon aimed at ``pos + sad·axis + a₁·e1 + a₂·e2`` (uniform fluence on that plane, see
:mod:`tetdose.plan.beams`).

Dynamic linac segment (a control-point interval in which the machine moves, see
:mod:`tetdose.plan.segments`): the meterset fraction t ∈ [0, 1] is drawn with density
A(t)/Ā by rejection (t uniform, accepted with probability A(t)/A_max, A the open area of the
interpolated aperture); the machine is put at t — gantry θ₀ + t·Δθ, collimator, couch likewise,
isocentre, jaws and leaves linearly — a leaf pair is chosen by its open area and a point
(a₁, a₂) uniform in it; the photon starts at ``iso + sad·Z_b`` and aims at
``iso + a₁·X_b + a₂·Y_b``, with (X_b, Y_b, Z_b) = M·R_z(−couch)·R_y(gantry)·R_z(collimator)
(IEC 61217, :func:`tetdose.plan.beams.beam_axes`; M maps the patient support system to the
source frame).

Quasi-random primaries (``TransportSettings.quasi_random``, :mod:`.quasi`): ``q`` is the
history's point of a scrambled Sobol sequence (:data:`N_QMC_DIMS` coordinates in [0, 1)); the
uniforms listed below are then taken from it instead of the history's stream (the stream still
advances by the same draws, so everything after the source is drawn as without it). Coordinates:
:data:`Q_A`, :data:`Q_B` the field position (parallel), cos θ and φ (point), the aperture point
(linac); :data:`Q_ENERGY` the spectrum line; :data:`Q_C` the aperture rectangle (linac);
:data:`Q_BEAM` the beam. Dynamic segments (rejection sampling) stay pseudo-random. Three more
coordinates are not the source's: with splitting along the ray, the source photon's split takes
its copies' common offset ξ (:data:`Q_SPLIT`, :mod:`tetdose.transport.history._split`) and its
shared interaction's Compton scatter (:data:`Q_COMPTON`, by inversion of the Klein–Nishina CDF,
:func:`tetdose.transport.physics._photon.klein_nishina_inverse`) and azimuth
(:data:`Q_AZIMUTH`) from the point, so the electrons the primaries set in motion have their
energies and directions spread evenly too. ``q`` of length 0: every uniform from the stream (bit
for bit the sampling without the option).
"""

import math
from typing import NamedTuple

from tetdose._jit import kernel
from tetdose._random import next_uniform, next_uniform_or
from tetdose._typing import FloatArray, IntArray

PENCIL, PARALLEL, POINT, LINAC, LINAC_DYNAMIC = 0, 1, 2, 3, 4
#: Rejection tries for a dynamic segment's meterset fraction; the acceptance is Ā/A_max (> 0.1
#: for any sensible segment), so the cap is a guard, never reached in practice.
MAX_TRIES = 10_000


class SourceArrays(NamedTuple):
    """Beams as flat arrays (positions [mm], unit vectors, energies [MeV])."""

    kind: IntArray  # (B,) PENCIL | PARALLEL | POINT | LINAC
    pos: FloatArray  # (B, 3)
    axis: FloatArray  # (B, 3)
    e1: FloatArray  # (B, 3) field x direction (⊥ axis)
    e2: FloatArray  # (B, 3) field y direction (axis × e1)
    field: FloatArray  # (B, 2) parallel field size [mm]
    cos_half: FloatArray  # (B,) cosine of the cone half angle
    beam_cdf: FloatArray  # (B,) cumulative beam probability
    spec_start: IntArray  # (B + 1,) offsets into spec_energy / spec_cdf
    spec_energy: FloatArray  # (K,) line energies [MeV]
    spec_cdf: FloatArray  # (K,) cumulative line probability within each beam
    sad: FloatArray  # (B,) linac source–isocentre distance [mm] (0 for other kinds)
    rect_start: IntArray  # (B + 1,) offsets into rect / rect_cdf (empty for other kinds)
    rect: FloatArray  # (R, 4) aperture rectangles [x1, x2, y1, y2] on the isocentre plane [mm]
    rect_cdf: FloatArray  # (R,) cumulative rectangle probability (by area) within each beam
    # Dynamic linac segments (kind LINAC_DYNAMIC: control-point intervals in which the machine
    # moves), J of them; flat fields, since numba's parallel loops take no nested tuples.
    dyn_row: IntArray  # (B,) segment index of source row b, −1 for every other kind
    dyn_angles: FloatArray  # (J, 6) gantry, collimator, couch at the start, then their turns [deg]
    dyn_iso: FloatArray  # (J, 6) isocentre at the start, then at the end [mm, source frame]
    dyn_jaws: FloatArray  # (J, 8) x1, x2, y1, y2 at the start, then at the end [mm]
    dyn_rot: FloatArray  # (J, 3, 3) patient support system → source frame
    dyn_leaf_start: IntArray  # (J,) offset into leaf0 / leaf1 (2N values: bank 1, then bank 2)
    dyn_n_pairs: IntArray  # (J,) leaf pairs N (0: jaws only)
    dyn_bnd_start: IntArray  # (J,) offset into bnd (N + 1 leaf boundaries)
    dyn_mlc_y: IntArray  # (J,) 1: leaves travel along Y_b (MLCY), 0: along X_b (MLCX)
    dyn_leaf0: FloatArray  # (L,) leaf positions at the start [mm]
    dyn_leaf1: FloatArray  # (L,) leaf positions at the end [mm]
    dyn_bnd: FloatArray  # (K,) leaf boundaries [mm]
    dyn_max_area: FloatArray  # (J,) largest open area over the segment [mm²] (rejection bound)


#: Coordinates of a history's quasi-random point (module docstring); Sobol's first dimensions are
#: the best distributed, so the field position comes first, the source photon's split last.
Q_A, Q_B, Q_ENERGY, Q_C, Q_BEAM, Q_SPLIT, Q_COMPTON, Q_AZIMUTH = 0, 1, 2, 3, 4, 5, 6, 7
N_QMC_DIMS = 8


@kernel
def _uniform(state, q, k):
    """(state, ξ): the stream's next uniform, replaced by coordinate k of ``q`` when it has one."""
    return next_uniform_or(state, q[k] if k < q.shape[0] else -1.0)


@kernel
def sample_source(src, state, q):
    """(state, energy, x, y, z, u, v, w) of one source photon; ``q`` the history's quasi-random
    point, or empty (module docstring)."""
    state, xi = _uniform(state, q, Q_BEAM)
    b = 0
    while b < src.beam_cdf.shape[0] - 1 and src.beam_cdf[b] <= xi:
        b += 1
    state, xi = _uniform(state, q, Q_ENERGY)
    i = src.spec_start[b]
    while i < src.spec_start[b + 1] - 1 and src.spec_cdf[i] <= xi:
        i += 1
    e = src.spec_energy[i]
    x, y, z = src.pos[b, 0], src.pos[b, 1], src.pos[b, 2]
    u, v, w = src.axis[b, 0], src.axis[b, 1], src.axis[b, 2]
    if src.kind[b] == PARALLEL:
        state, r1 = _uniform(state, q, Q_A)
        state, r2 = _uniform(state, q, Q_B)
        a1 = (r1 - 0.5) * src.field[b, 0]
        a2 = (r2 - 0.5) * src.field[b, 1]
        x += a1 * src.e1[b, 0] + a2 * src.e2[b, 0]
        y += a1 * src.e1[b, 1] + a2 * src.e2[b, 1]
        z += a1 * src.e1[b, 2] + a2 * src.e2[b, 2]
    elif src.kind[b] == POINT:
        state, r1 = _uniform(state, q, Q_A)
        state, r2 = _uniform(state, q, Q_B)
        ct = 1.0 - r1 * (1.0 - src.cos_half[b])
        st = math.sqrt(max(1.0 - ct * ct, 0.0))
        cp, sp = math.cos(2.0 * math.pi * r2), math.sin(2.0 * math.pi * r2)
        u = ct * u + st * (cp * src.e1[b, 0] + sp * src.e2[b, 0])
        v = ct * v + st * (cp * src.e1[b, 1] + sp * src.e2[b, 1])
        w = ct * w + st * (cp * src.e1[b, 2] + sp * src.e2[b, 2])
        norm = math.sqrt(u * u + v * v + w * w)
        u, v, w = u / norm, v / norm, w / norm
    elif src.kind[b] == LINAC:
        state, u, v, w = _aim_in_aperture(src, b, state, q)
    elif src.kind[b] == LINAC_DYNAMIC:
        state, x, y, z, u, v, w = _dynamic_photon(src, src.dyn_row[b], src.sad[b], state)
    return state, e, x, y, z, u, v, w


@kernel
def _aim_in_aperture(src, b, state, q):
    """(state, u, v, w): unit direction from the source of linac beam b to a point drawn
    uniformly over its aperture on the isocentre plane (rectangle by area, then uniform)."""
    state, xi = _uniform(state, q, Q_C)
    r = src.rect_start[b]
    while r < src.rect_start[b + 1] - 1 and src.rect_cdf[r] <= xi:
        r += 1
    state, r1 = _uniform(state, q, Q_A)
    state, r2 = _uniform(state, q, Q_B)
    a1 = src.rect[r, 0] + r1 * (src.rect[r, 1] - src.rect[r, 0])
    a2 = src.rect[r, 2] + r2 * (src.rect[r, 3] - src.rect[r, 2])
    d = src.sad[b]
    u = d * src.axis[b, 0] + a1 * src.e1[b, 0] + a2 * src.e2[b, 0]
    v = d * src.axis[b, 1] + a1 * src.e1[b, 1] + a2 * src.e2[b, 1]
    w = d * src.axis[b, 2] + a1 * src.e1[b, 2] + a2 * src.e2[b, 2]
    norm = math.sqrt(u * u + v * v + w * w)
    return state, u / norm, v / norm, w / norm


@kernel
def _pair_rect(src, j, t, i):
    """(x1, x2, y1, y2) [mm] of leaf pair i of dynamic segment j at fraction t, cut by the
    jaws (x2 ≤ x1 or y2 ≤ y1: closed); without MLC the jaws."""
    jw = src.dyn_jaws
    x1 = jw[j, 0] + t * (jw[j, 4] - jw[j, 0])
    x2 = jw[j, 1] + t * (jw[j, 5] - jw[j, 1])
    y1 = jw[j, 2] + t * (jw[j, 6] - jw[j, 2])
    y2 = jw[j, 3] + t * (jw[j, 7] - jw[j, 3])
    n = src.dyn_n_pairs[j]
    if n == 0:
        return x1, x2, y1, y2
    k = src.dyn_leaf_start[j] + i
    lo = src.dyn_leaf0[k] + t * (src.dyn_leaf1[k] - src.dyn_leaf0[k])
    hi = src.dyn_leaf0[k + n] + t * (src.dyn_leaf1[k + n] - src.dyn_leaf0[k + n])
    b0, b1 = src.dyn_bnd[src.dyn_bnd_start[j] + i], src.dyn_bnd[src.dyn_bnd_start[j] + i + 1]
    if src.dyn_mlc_y[j] == 0:
        return max(x1, lo), min(x2, hi), max(y1, b0), min(y2, b1)
    return max(x1, b0), min(x2, b1), max(y1, lo), min(y2, hi)


@kernel
def _open_area(src, j, t):
    """Open area [mm²] of dynamic segment j at fraction t."""
    area = 0.0
    for i in range(max(src.dyn_n_pairs[j], 1)):
        x1, x2, y1, y2 = _pair_rect(src, j, t, i)
        area += max(x2 - x1, 0.0) * max(y2 - y1, 0.0)
    return area


@kernel
def _point_in_aperture(src, j, t, area, state):
    """(state, a1, a2): a point uniform over the open aperture of segment j at t [mm]."""
    state, xi = next_uniform(state)
    target = xi * area
    acc = 0.0
    x1 = x2 = y1 = y2 = 0.0
    for i in range(max(src.dyn_n_pairs[j], 1)):
        p1, p2, q1, q2 = _pair_rect(src, j, t, i)
        a = max(p2 - p1, 0.0) * max(q2 - q1, 0.0)
        if a > 0.0:
            x1, x2, y1, y2 = p1, p2, q1, q2
            acc += a
            if acc > target:
                break
    state, r1 = next_uniform(state)
    state, r2 = next_uniform(state)
    return state, x1 + r1 * (x2 - x1), y1 + r2 * (y2 - y1)


@kernel
def _support_to_frame(rot, j, ct, st, vx, vy, vz):
    """rot[j] · R_z(−couch) · v for a vector v of the fixed system (ct, st: cos, sin couch)."""
    sx = ct * vx + st * vy
    sy = -st * vx + ct * vy
    return (rot[j, 0, 0] * sx + rot[j, 0, 1] * sy + rot[j, 0, 2] * vz,
            rot[j, 1, 0] * sx + rot[j, 1, 1] * sy + rot[j, 1, 2] * vz,
            rot[j, 2, 0] * sx + rot[j, 2, 1] * sy + rot[j, 2, 2] * vz)


@kernel
def _dynamic_photon(src, j, sad, state):
    """(state, x, y, z, u, v, w): a photon of dynamic segment j (see module doc)."""
    t = 0.0
    area = 0.0
    for _ in range(MAX_TRIES):
        state, t = next_uniform(state)
        area = _open_area(src, j, t)
        state, xi = next_uniform(state)
        if xi * src.dyn_max_area[j] < area:
            break
    state, a1, a2 = _point_in_aperture(src, j, t, area, state)
    g = math.radians(src.dyn_angles[j, 0] + t * src.dyn_angles[j, 3])
    c = math.radians(src.dyn_angles[j, 1] + t * src.dyn_angles[j, 4])
    u = math.radians(src.dyn_angles[j, 2] + t * src.dyn_angles[j, 5])
    cg, sg, cc, sc = math.cos(g), math.sin(g), math.cos(c), math.sin(c)
    cu, su = math.cos(u), math.sin(u)
    # Columns of R_y(gantry)·R_z(collimator): X_b, Y_b, Z_b in the fixed system.
    xx, xy, xz = _support_to_frame(src.dyn_rot, j, cu, su, cg * cc, sc, -sg * cc)
    yx, yy, yz = _support_to_frame(src.dyn_rot, j, cu, su, -cg * sc, cc, sg * sc)
    zx, zy, zz = _support_to_frame(src.dyn_rot, j, cu, su, sg, 0.0, cg)
    ix = src.dyn_iso[j, 0] + t * (src.dyn_iso[j, 3] - src.dyn_iso[j, 0])
    iy = src.dyn_iso[j, 1] + t * (src.dyn_iso[j, 4] - src.dyn_iso[j, 1])
    iz = src.dyn_iso[j, 2] + t * (src.dyn_iso[j, 5] - src.dyn_iso[j, 2])
    dx = a1 * xx + a2 * yx - sad * zx
    dy = a1 * xy + a2 * yy - sad * zy
    dz = a1 * xz + a2 * yz - sad * zz
    norm = math.sqrt(dx * dx + dy * dy + dz * dz)
    return (state, ix + sad * zx, iy + sad * zy, iz + sad * zz, dx / norm, dy / norm,
            dz / norm)
