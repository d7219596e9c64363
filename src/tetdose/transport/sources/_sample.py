"""njit source sampling: one source photon's (energy, position, direction) from flat beam arrays.

Source sampling: beam b is chosen with probability w_b/Σw (cumulative ``beam_cdf``), its energy
from the discrete lines of its spectrum (cumulative ``spec_cdf``). Pencil: fixed point and
direction. Parallel: uniform on the rectangle ``pos + (ξ₁−½)·fx·e1 + (ξ₂−½)·fy·e2``. Point: cone
about the axis, cos θ uniform on [cos θ_half, 1], φ uniform (isotropic for θ_half = 180°).
Linac: a point source at ``pos``; a rectangle r of the beam's aperture is chosen with probability
area_r/Σarea (cumulative ``rect_cdf``), a point (a₁, a₂) uniform in it on the isocentre plane, and
the photon aimed at ``pos + sad·axis + a₁·e1 + a₂·e2`` (uniform fluence on that plane, see
:mod:`tetdose.plan.beams`).
"""

import math
from typing import NamedTuple

from tetdose._jit import kernel
from tetdose._random import next_uniform
from tetdose._typing import FloatArray, IntArray

PENCIL, PARALLEL, POINT, LINAC = 0, 1, 2, 3


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


@kernel
def sample_source(src, state):
    """(state, energy, x, y, z, u, v, w) of one source photon."""
    state, xi = next_uniform(state)
    b = 0
    while b < src.beam_cdf.shape[0] - 1 and src.beam_cdf[b] <= xi:
        b += 1
    state, xi = next_uniform(state)
    i = src.spec_start[b]
    while i < src.spec_start[b + 1] - 1 and src.spec_cdf[i] <= xi:
        i += 1
    e = src.spec_energy[i]
    x, y, z = src.pos[b, 0], src.pos[b, 1], src.pos[b, 2]
    u, v, w = src.axis[b, 0], src.axis[b, 1], src.axis[b, 2]
    if src.kind[b] == PARALLEL:
        state, r1 = next_uniform(state)
        state, r2 = next_uniform(state)
        a1 = (r1 - 0.5) * src.field[b, 0]
        a2 = (r2 - 0.5) * src.field[b, 1]
        x += a1 * src.e1[b, 0] + a2 * src.e2[b, 0]
        y += a1 * src.e1[b, 1] + a2 * src.e2[b, 1]
        z += a1 * src.e1[b, 2] + a2 * src.e2[b, 2]
    elif src.kind[b] == POINT:
        state, r1 = next_uniform(state)
        state, r2 = next_uniform(state)
        ct = 1.0 - r1 * (1.0 - src.cos_half[b])
        st = math.sqrt(max(1.0 - ct * ct, 0.0))
        cp, sp = math.cos(2.0 * math.pi * r2), math.sin(2.0 * math.pi * r2)
        u = ct * u + st * (cp * src.e1[b, 0] + sp * src.e2[b, 0])
        v = ct * v + st * (cp * src.e1[b, 1] + sp * src.e2[b, 1])
        w = ct * w + st * (cp * src.e1[b, 2] + sp * src.e2[b, 2])
        norm = math.sqrt(u * u + v * v + w * w)
        u, v, w = u / norm, v / norm, w / norm
    elif src.kind[b] == LINAC:
        state, u, v, w = _aim_in_aperture(src, b, state)
    return state, e, x, y, z, u, v, w


@kernel
def _aim_in_aperture(src, b, state):
    """(state, u, v, w): unit direction from the source of linac beam b to a point drawn
    uniformly over its aperture on the isocentre plane (rectangle by area, then uniform)."""
    state, xi = next_uniform(state)
    r = src.rect_start[b]
    while r < src.rect_start[b + 1] - 1 and src.rect_cdf[r] <= xi:
        r += 1
    state, r1 = next_uniform(state)
    state, r2 = next_uniform(state)
    a1 = src.rect[r, 0] + r1 * (src.rect[r, 1] - src.rect[r, 0])
    a2 = src.rect[r, 2] + r2 * (src.rect[r, 3] - src.rect[r, 2])
    d = src.sad[b]
    u = d * src.axis[b, 0] + a1 * src.e1[b, 0] + a2 * src.e2[b, 0]
    v = d * src.axis[b, 1] + a1 * src.e1[b, 1] + a2 * src.e2[b, 1]
    w = d * src.axis[b, 2] + a1 * src.e1[b, 2] + a2 * src.e2[b, 2]
    norm = math.sqrt(u * u + v * v + w * w)
    return state, u / norm, v / norm, w / norm
