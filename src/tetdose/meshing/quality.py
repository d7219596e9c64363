"""Sliver removal after MMG (which optimises a radius-ratio quality and can leave a few flat
tetrahedra with good edges at curved surfaces and ridges): guarded vertex relocation, then
topological moves (:mod:`tetdose.meshing.flips`), each followed by relocation again.

Relocation. For every tetrahedron whose smallest dihedral angle is below the threshold, each of
its vertices that may move is relocated by a compass search maximising the smallest dihedral
angle of its star (Freitag & Ollivier-Gooch, IJNME 40 (1997) 3979: local optimisation of the
worst angle), first reducing the number of the star's tetrahedra below the threshold:
candidates are the ideal position — the mean over the star of the apex of the regular
tetrahedron on the opposite face, c_f + n_f·√(2/3)·ē_f — and steps along 14 directions (axes
and diagonals), halving from ½ of the mean edge; a move is kept only when it raises the star's
smallest angle with every volume positive.

Free vertices (inside one region) move in 3-D. A vertex on exactly one surface (the outer
boundary or one interface) where that surface is smooth (its faces' normals within
``SMOOTH_DEG`` of their mean n) moves in the tangent plane only, x + (I − n nᵀ) d, which keeps
it within about |d|²κ/2 of the surface. Vertices on junctions of surfaces or ridges are fixed
in the first rounds, so conformity is unchanged and volumes change by that second-order term
only.

Topology. Three rounds of edge removal / 2-3 flips inside one region and reassignment of flat
surface tetrahedra (flips.py), each followed by relocation; in the second and third rounds the
fixed vertices of the tetrahedra still bad may move too, in 3-D, at most 0.2 and then 0.35 of
their star's mean longest edge (``FIXED_MOVE_FRACTIONS``: a bounded surface deviation, for the
few slivers whose free vertices cannot fix them). A last relocation of what is still bad drops
the count term and maximises the star's smallest angle alone (Freitag & Ollivier-Gooch's
max-min): neighbours may fall below the aim (12°) but never below the worst angle, which rises.
Faces are never shared by more than two tetrahedra, so the mesh stays conforming.
"""

from __future__ import annotations

import numpy as np

from tetdose._typing import FloatArray, IntArray
from tetdose.core.mesh import FACE_VERTICES, signed_volumes_mm3
from tetdose.meshing._relocation_kernels import compass_search, min_dihedral_vol6

#: Relocation rounds over the remaining bad tetrahedra.
ROUNDS = 3
#: Compass-search iterations per vertex.
SEARCH_ITERATIONS = 30
#: Per round of topological moves (flips.py, then relocation): how far junction and ridge
#: vertices of the remaining bad tetrahedra may move, as a fraction of their star's mean longest
#: edge (0: fixed). Escalating, so that only the most stubborn slivers move them far.
FIXED_MOVE_FRACTIONS = (0.0, 0.2, 0.35)
#: A surface vertex slides only where its faces' normals are within this angle of their mean.
SMOOTH_DEG = 25.0

#: Search directions: the 6 axes and 8 diagonals (unit vectors).
_DIRS = np.array([d for d in np.ndindex(3, 3, 3) if d != (1, 1, 1)], dtype=np.float64) - 1.0
_DIRS = _DIRS[np.abs(_DIRS).sum(axis=1) != 2]
_DIRS /= np.linalg.norm(_DIRS, axis=1)[:, None]


def _cross(a: FloatArray, b: FloatArray) -> FloatArray:
    """a × b over the last axis (componentwise: fewer temporaries than np.cross)."""
    return np.stack([a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
                     a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
                     a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]], axis=-1)


def _min_dihedral(points_mm: FloatArray, tets: IntArray) -> FloatArray:
    return min_dihedral_vol6(points_mm, np.asarray(tets, dtype=np.intp).reshape(-1, 4))[0]


def _stars(n_points: int, tets: IntArray) -> tuple[IntArray, IntArray]:
    """CSR (offsets, tet ids) of the tetrahedra around each vertex."""
    flat = tets.ravel()
    order = np.argsort(flat, kind="stable")
    offsets = np.zeros(n_points + 1, dtype=np.intp)
    np.cumsum(np.bincount(flat, minlength=n_points), out=offsets[1:])
    return offsets, order // 4


def removed_slivers(points_mm: FloatArray, tets: IntArray, region: IntArray,
                    min_dihedral_deg: float) -> tuple[FloatArray, IntArray, IntArray]:
    """(points, tets, region) with the slivers below ``min_dihedral_deg`` [°] removed (module
    doc): relocation of the free and smooth-surface vertices, then rounds of topological moves
    (:func:`tetdose.meshing.flips.flipped`) each followed by relocation, the later rounds also
    moving junction and ridge vertices within ``FIXED_MOVE_FRACTIONS`` of their edges."""
    from tetdose.meshing.flips import flipped

    tets = np.asarray(tets, dtype=np.intp)
    region = np.asarray(region, dtype=np.int64)
    bad = np.flatnonzero(_min_dihedral(points_mm, tets) < min_dihedral_deg)
    points, bad = relocated(points_mm, tets, region, min_dihedral_deg, bad)
    flips = True
    for bound in FIXED_MOVE_FRACTIONS:
        if bad.size == 0:
            break
        if flips:
            t, r, b = flipped(points, tets, region, min_dihedral_deg, bad)
            flips = _valid_topology(points, t)
            if flips:  # else keep the round's input: relocation alone from here on
                tets, region, bad = t, r, b
        points, bad = relocated(points, tets, region, min_dihedral_deg, bad,
                                fixed_move_fraction=bound)
    if bad.size:  # last resort: the worst angle alone, even if neighbours drop below the aim
        points, bad = relocated(points, tets, region, min_dihedral_deg, bad,
                                fixed_move_fraction=FIXED_MOVE_FRACTIONS[-1], count_weight=0.0)
    used = np.zeros(len(points), dtype=bool)
    used[tets.ravel()] = True
    if not used.all():  # a deleted corner tetrahedron can leave its apex unused
        new_id = np.cumsum(used) - 1
        points, tets = points[used], new_id[tets]
    return points, tets, region


def _valid_topology(points_mm: FloatArray, tets: IntArray) -> bool:
    """Every face shared by at most two tetrahedra and every volume positive: the guard that
    keeps a faulty topological round out of the mesh (it is then undone, not repaired)."""
    if not np.all(signed_volumes_mm3(points_mm, tets) > 0):
        return False
    f = np.sort(tets[:, FACE_VERTICES].reshape(-1, 3), axis=1)
    f = f[np.lexsort(f.T[::-1])]
    same = np.all(f[1:] == f[:-1], axis=1)
    return not np.any(same[1:] & same[:-1])  # three equal faces in a row


def relocated(points_mm: FloatArray, tets: IntArray, region: IntArray, min_dihedral_deg: float,
              bad: IntArray, *, fixed_move_fraction: float = 0.0, count_weight: float = 1000.0
              ) -> tuple[FloatArray, IntArray]:
    """(points with the vertices of the bad tetrahedra ``bad`` relocated (module doc), ids of
    the tetrahedra still below ``min_dihedral_deg``); tets unchanged. With
    ``fixed_move_fraction`` > 0 the fixed vertices (junctions, ridges) move too, in 3-D but at
    most that fraction of their star's mean longest edge from where they are. ``count_weight``
    [°] is subtracted from a star's score per tetrahedron below ``min_dihedral_deg``."""
    points = points_mm.copy()
    if bad.size == 0:
        return points, bad
    offsets, star_tets = _stars(len(points), tets)
    frames: dict[int, tuple[bool, FloatArray]] = {}
    for _ in range(ROUNDS):
        touched = []
        for v in np.unique(tets[bad]).tolist():
            star = star_tets[offsets[v]:offsets[v + 1]]
            if v not in frames:  # the surface normal at the start of the pass
                frames[v] = _frame(points, tets, region, star, v)
            fixed, projector = frames[v]
            if fixed and fixed_move_fraction <= 0:
                continue
            if fixed:
                x = _relocated(points, tets, star, v, np.eye(3), min_dihedral_deg,
                               fixed_move_fraction, count_weight)
            else:
                x = _relocated(points, tets, star, v, projector, min_dihedral_deg, np.inf,
                               count_weight)
            if np.any(x != points[v]):
                points[v] = x
                touched.append(star)
        if not touched:
            break
        near = np.union1d(bad, np.concatenate(touched))  # a move may worsen a neighbour
        bad = near[_min_dihedral(points, tets[near]) < min_dihedral_deg]
        if bad.size == 0:
            break
    return points, bad


def _frame(points_mm: FloatArray, tets: IntArray, region: IntArray, star: IntArray, v: int
           ) -> tuple[bool, FloatArray]:
    """Whether vertex ``v`` is fixed, and the projector (3, 3) of its allowed moves (module
    doc), from the faces through ``v`` of its star ``star``: a face there once is on the outer
    boundary, twice with two regions on an interface (oriented from the higher region)."""
    st = tets[star]
    local = np.argmax(st == v, axis=1)
    f = np.arange(4)[None, :] != local[:, None]  # faces through v
    which = np.nonzero(f)
    faces = st[which[0][:, None], FACE_VERTICES[which[1]]]  # (3S, 3), outward
    own = region[star][which[0]]
    key = np.sort(faces, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    lo = np.full(len(counts), np.iinfo(np.int64).max)
    hi = np.full(len(counts), -1, dtype=np.int64)
    np.minimum.at(lo, inverse, own)
    np.maximum.at(hi, inverse, own)
    single = counts[inverse] == 1
    surface = single | (lo[inverse] != hi[inverse])
    keep = surface & (single | (own == hi[inverse]))  # each interface face from its higher side
    if not keep.any():
        return False, np.eye(3)
    other = np.where(single, -1, lo[inverse])
    codes = np.unique(own[keep] * (int(region.max()) + 2) + other[keep] + 1)
    p = points_mm[faces[keep]]
    area = _cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    n = area.sum(axis=0)
    n /= max(float(np.linalg.norm(n)), 1e-300)
    unit = area / np.maximum(np.linalg.norm(area, axis=1), 1e-300)[:, None]
    smooth = float((unit @ n).min()) >= np.cos(np.radians(SMOOTH_DEG))
    return len(codes) > 1 or not smooth, np.eye(3) - np.outer(n, n)


def _ideal(points_mm: FloatArray, tets: IntArray, star: IntArray, v: int) -> FloatArray:
    """Mean apex position of regular tetrahedra on the faces opposite ``v`` in its star."""
    local = np.argmax(tets[star] == v, axis=1)
    face = tets[star[:, None], FACE_VERTICES[local]]  # oriented outwards, i.e. away from v
    p = points_mm[face]
    normal = -np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    normal /= np.linalg.norm(normal, axis=1)[:, None]
    edge = np.linalg.norm(p - np.roll(p, 1, axis=1), axis=2).mean(axis=1)
    return (p.mean(axis=1) + normal * np.sqrt(2.0 / 3.0) * edge[:, None]).mean(axis=0)


def _relocated(points_mm: FloatArray, tets: IntArray, star: IntArray, v: int,
               projector: FloatArray, threshold_deg: float, bound_fraction: float = np.inf,
               count_weight: float = 1000.0) -> FloatArray:
    """Compass search (module doc) for the position of ``v``, moves projected by ``projector``
    and kept within ``bound_fraction`` × the star's mean longest edge of the start."""
    star_tets = tets[star]
    star_pts = points_mm[star_tets]
    edge = float(np.linalg.norm(star_pts - points_mm[v], axis=2).max(axis=1).mean())
    dirs = _DIRS @ projector
    dirs = np.ascontiguousarray(dirs[np.linalg.norm(dirs, axis=1) > 0.3])
    slot = np.argmax(star_tets == v, axis=1)
    ideal = _ideal(points_mm, tets, star, v)
    return compass_search(star_pts, slot, points_mm[v].copy(), ideal, dirs,
                          np.ascontiguousarray(projector), edge, bound_fraction * edge,
                          threshold_deg, count_weight, SEARCH_ITERATIONS)
