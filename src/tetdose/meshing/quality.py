"""Sliver removal by guarded vertex relocation (after MMG, which optimises a radius-ratio
quality and can leave a few flat tetrahedra with good edges at curved surfaces and ridges).

For every tetrahedron whose smallest dihedral angle is below the threshold, each of its vertices
that may move is relocated by a compass search maximising the smallest dihedral angle of its
star (Freitag & Ollivier-Gooch, IJNME 40 (1997) 3979: local optimisation of the worst angle),
first reducing the number of the star's tetrahedra below the threshold:
candidates are the ideal position — the mean over the star of the apex of the regular
tetrahedron on the opposite face, c_f + n_f·√(2/3)·ē_f — and steps along 14 directions (axes
and diagonals), halving from ½ of the mean edge; a move is kept only when it raises the star's
smallest angle with every volume positive.

Free vertices (inside one region) move in 3-D. A vertex on exactly one surface (the outer
boundary or one interface) where that surface is smooth (its faces' normals within
``SMOOTH_DEG`` of their mean n) moves in the tangent plane only, x + (I − n nᵀ) d, which keeps
it within about |d|²κ/2 of the surface. Vertices on junctions of surfaces or ridges never move,
so conformity is unchanged and volumes change by that second-order term only.
"""

from __future__ import annotations

import numpy as np

from tetdose._typing import FloatArray, IntArray
from tetdose.mesh import FACE_VERTICES, signed_volumes_mm3

#: Relocation rounds over the remaining bad tetrahedra.
ROUNDS = 3
#: Compass-search iterations per vertex.
SEARCH_ITERATIONS = 30
#: Rounds of topological moves (flips.py), each followed by relocation.
TOPOLOGY_ROUNDS = 3
#: After the first round, junction and ridge vertices of the remaining bad tetrahedra move
#: within this fraction of their star's mean longest edge.
FIXED_MOVE_FRACTION = 0.2
#: A surface vertex slides only where its faces' normals are within this angle of their mean.
SMOOTH_DEG = 25.0

#: Search directions: the 6 axes and 8 diagonals (unit vectors).
_DIRS = np.array([d for d in np.ndindex(3, 3, 3) if d != (1, 1, 1)], dtype=np.float64) - 1.0
_DIRS = _DIRS[np.abs(_DIRS).sum(axis=1) != 2]
_DIRS /= np.linalg.norm(_DIRS, axis=1)[:, None]


def _min_dihedral(points_mm: FloatArray, tets: IntArray) -> FloatArray:
    from tetdose.meshing.checks import dihedral_angles_deg

    return dihedral_angles_deg(points_mm, tets).min(axis=1)


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
    moving junction and ridge vertices within ``FIXED_MOVE_FRACTION`` of their edges."""
    from tetdose.meshing.flips import flipped

    tets = np.asarray(tets, dtype=np.intp)
    region = np.asarray(region, dtype=np.int64)
    points = relocated(points_mm, tets, region, min_dihedral_deg)
    for k in range(TOPOLOGY_ROUNDS):
        bad = np.flatnonzero(_min_dihedral(points, tets) < min_dihedral_deg)
        if bad.size == 0:
            break
        tets, region = flipped(points, tets, region, min_dihedral_deg, bad)
        bound = FIXED_MOVE_FRACTION if k > 0 else 0.0
        points = relocated(points, tets, region, min_dihedral_deg, fixed_move_fraction=bound)
    used = np.zeros(len(points), dtype=bool)
    used[tets.ravel()] = True
    if not used.all():  # a deleted corner tetrahedron can leave its apex unused
        new_id = np.cumsum(used) - 1
        points, tets = points[used], new_id[tets]
    return points, tets, region


def relocated(points_mm: FloatArray, tets: IntArray, region: IntArray, min_dihedral_deg: float,
              *, fixed_move_fraction: float = 0.0) -> FloatArray:
    """Points with the vertices of bad tetrahedra relocated (module doc); tets unchanged.
    With ``fixed_move_fraction`` > 0 the fixed vertices (junctions, ridges) move too, in 3-D
    but at most that fraction of their star's mean longest edge from where they are."""
    points = points_mm.copy()
    bad = np.flatnonzero(_min_dihedral(points, tets) < min_dihedral_deg)
    if bad.size == 0:
        return points
    offsets, star_tets = _stars(len(points), tets)
    fixed, projector = _frames(points, tets, region)
    for _ in range(ROUNDS):
        for v in np.unique(tets[bad]).tolist():
            star = star_tets[offsets[v]:offsets[v + 1]]
            if not fixed[v]:
                points[v] = _relocated(points, tets, star, v, projector[v], min_dihedral_deg)
            elif fixed_move_fraction > 0:
                points[v] = _relocated(points, tets, star, v, np.eye(3), min_dihedral_deg,
                                       fixed_move_fraction)
        bad = bad[_min_dihedral(points, tets[bad]) < min_dihedral_deg]
        if bad.size == 0:
            break
    return points


def _frames(points_mm: FloatArray, tets: IntArray, region: IntArray
            ) -> tuple[np.ndarray, FloatArray]:
    """Per vertex: fixed? and the projector (N, 3, 3) of its allowed moves (module doc)."""
    n = len(points_mm)
    faces = tets[:, FACE_VERTICES].reshape(-1, 3)
    key = np.sort(faces, axis=1)
    order = np.lexsort(key.T[::-1])
    same = np.all(key[order][1:] == key[order][:-1], axis=1)
    own = np.repeat(region, 4)
    other = np.full(len(faces), -1, dtype=np.int64)
    first, second = order[:-1][same], order[1:][same]
    other[first], other[second] = own[second], own[first]
    keep = own > other  # boundary faces (other = −1) and each interface once, from its higher side
    faces, code = faces[keep], own[keep] * (int(region.max()) + 2) + other[keep] + 1
    lo = np.full(n, np.iinfo(np.int64).max)
    hi = np.full(n, -1, dtype=np.int64)
    np.minimum.at(lo, faces.ravel(), np.repeat(code, 3))
    np.maximum.at(hi, faces.ravel(), np.repeat(code, 3))
    p = points_mm[faces]
    area_normal = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    normal = np.zeros((n, 3))
    for c in range(3):
        np.add.at(normal, faces[:, c], area_normal)
    normal /= np.maximum(np.linalg.norm(normal, axis=1), 1e-300)[:, None]
    unit = area_normal / np.maximum(np.linalg.norm(area_normal, axis=1), 1e-300)[:, None]
    cos = np.ones(n)
    for c in range(3):
        np.minimum.at(cos, faces[:, c], np.einsum("ij,ij->i", unit, normal[faces[:, c]]))
    on_surface = hi >= 0
    fixed = on_surface & ((lo != hi) | (cos < np.cos(np.radians(SMOOTH_DEG))))
    projector = np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
    projector[on_surface] -= normal[on_surface, :, None] * normal[on_surface, None, :]
    return fixed, projector


def _ideal(points_mm: FloatArray, tets: IntArray, star: IntArray, v: int) -> FloatArray:
    """Mean apex position of regular tetrahedra on the faces opposite ``v`` in its star."""
    local = np.argmax(tets[star] == v, axis=1)
    face = tets[star[:, None], FACE_VERTICES[local]]  # oriented outwards, i.e. away from v
    p = points_mm[face]
    normal = -np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    normal /= np.linalg.norm(normal, axis=1)[:, None]
    edge = np.linalg.norm(p - np.roll(p, 1, axis=1), axis=2).mean(axis=1)
    return (p.mean(axis=1) + normal * np.sqrt(2.0 / 3.0) * edge[:, None]).mean(axis=0)


def _star_score(points_mm: FloatArray, star_tets: IntArray, v: int,
                candidates: FloatArray, threshold_deg: float) -> FloatArray:
    """Score of the star with ``v`` at each candidate position (C, 3): its smallest dihedral
    angle [°] minus 1000 per tetrahedron below ``threshold_deg`` (fewer bad ones first);
    −inf where a tetrahedron would invert."""
    p = np.broadcast_to(points_mm[star_tets], (len(candidates), *star_tets.shape, 3)).copy()
    slot = star_tets == v
    p[:, slot] = candidates[:, None, :]
    flat = p.reshape(-1, 3)
    ids = np.arange(len(flat)).reshape(-1, 4)
    angles = _min_dihedral(flat, ids).reshape(len(candidates), -1)
    vols = signed_volumes_mm3(flat, ids).reshape(len(candidates), -1)
    score = angles.min(axis=1) - 1000.0 * (angles < threshold_deg).sum(axis=1)
    return np.where((vols > 0).all(axis=1), score, -np.inf)


def _relocated(points_mm: FloatArray, tets: IntArray, star: IntArray, v: int,
               projector: FloatArray, threshold_deg: float, bound_fraction: float = np.inf
               ) -> FloatArray:
    """Compass search (module doc) for the position of ``v``, moves projected by ``projector``
    and kept within ``bound_fraction`` × the star's mean longest edge of the start."""
    star_tets = tets[star]
    edge = np.linalg.norm(points_mm[star_tets] - points_mm[v], axis=2).max(axis=1).mean()
    dirs = _DIRS @ projector
    dirs = dirs[np.linalg.norm(dirs, axis=1) > 0.3]
    x0 = points_mm[v].copy()
    x = x0.copy()
    radius = bound_fraction * edge
    best = _star_score(points_mm, star_tets, v, x[None], threshold_deg)[0]
    ideal = _ideal(points_mm, tets, star, v)
    step = min(0.5 * edge, radius)
    for _ in range(SEARCH_ITERATIONS):
        cand = np.concatenate([x + step * dirs, [x + 0.5 * projector @ (ideal - x)]])
        score = _star_score(points_mm, star_tets, v, cand, threshold_deg)
        score[np.linalg.norm(cand - x0, axis=1) > radius] = -np.inf
        i = int(np.argmax(score))
        if score[i] > best:
            best, x = score[i], cand[i]
        else:
            step *= 0.5
            if step < 0.02 * edge:
                break
    return x
