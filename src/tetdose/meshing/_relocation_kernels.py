"""Compiled compass search for one vertex position (the relocation of
:mod:`tetdose.meshing.quality`: Freitag & Ollivier-Gooch, IJNME 40 (1997) 3979).

Quality of a tetrahedron p_0…p_3 [mm]: with e_k = p_k − p_0, the outward area normals of the
faces opposite vertices 1, 2, 3 are n_1 = e_3 × e_2, n_2 = e_1 × e_3, n_3 = e_2 × e_1 and
n_0 = −(n_1 + n_2 + n_3); the dihedral angle between faces i and j is π − ∠(n_i, n_j), so the
smallest one is arccos(−min_{i<j} n̂_i · n̂_j); 6V = −e_1 · n_1.
"""

import math

import numpy as np
from numba import njit


@njit(cache=True)
def tet_min_dihedral_vol6(q: np.ndarray) -> tuple[float, float]:
    """(smallest dihedral angle [°], 6 × signed volume [mm³]) of the tetrahedron q (4, 3)."""
    e1x, e1y, e1z = q[1, 0] - q[0, 0], q[1, 1] - q[0, 1], q[1, 2] - q[0, 2]
    e2x, e2y, e2z = q[2, 0] - q[0, 0], q[2, 1] - q[0, 1], q[2, 2] - q[0, 2]
    e3x, e3y, e3z = q[3, 0] - q[0, 0], q[3, 1] - q[0, 1], q[3, 2] - q[0, 2]
    n = np.empty((4, 3))
    n[1, 0], n[1, 1], n[1, 2] = e3y * e2z - e3z * e2y, e3z * e2x - e3x * e2z, e3x * e2y - e3y * e2x
    n[2, 0], n[2, 1], n[2, 2] = e1y * e3z - e1z * e3y, e1z * e3x - e1x * e3z, e1x * e3y - e1y * e3x
    n[3, 0], n[3, 1], n[3, 2] = e2y * e1z - e2z * e1y, e2z * e1x - e2x * e1z, e2x * e1y - e2y * e1x
    vol6 = -(e1x * n[1, 0] + e1y * n[1, 1] + e1z * n[1, 2])
    for c in range(3):
        n[0, c] = -(n[1, c] + n[2, c] + n[3, c])
    for i in range(4):
        norm = math.sqrt(n[i, 0] ** 2 + n[i, 1] ** 2 + n[i, 2] ** 2)
        norm = max(norm, 1e-300)
        for c in range(3):
            n[i, c] /= norm
    worst = 1.0
    for i in range(4):
        for j in range(i + 1, 4):
            worst = min(worst, n[i, 0] * n[j, 0] + n[i, 1] * n[j, 1] + n[i, 2] * n[j, 2])
    return math.degrees(math.acos(min(1.0, max(-1.0, -worst)))), vol6


@njit(cache=True)
def star_score(star_pts: np.ndarray, slot: np.ndarray, x: np.ndarray, threshold_deg: float,
               count_weight: float) -> float:
    """Smallest dihedral angle [°] of the star (S, 4, 3) with vertex slot[s] of tet s at x,
    minus ``count_weight`` per tetrahedron below ``threshold_deg``; −inf if one is not
    positive."""
    q = np.empty((4, 3))
    worst = np.inf
    n_bad = 0
    for s in range(star_pts.shape[0]):
        for k in range(4):
            for c in range(3):
                q[k, c] = x[c] if k == slot[s] else star_pts[s, k, c]
        angle, vol6 = tet_min_dihedral_vol6(q)
        if not vol6 > 0.0:
            return -np.inf
        worst = min(worst, angle)
        if angle < threshold_deg:
            n_bad += 1
    return worst - count_weight * n_bad


@njit(cache=True)
def compass_search(star_pts: np.ndarray, slot: np.ndarray, x0: np.ndarray, ideal: np.ndarray,
                   dirs: np.ndarray, projector: np.ndarray, edge: float, radius: float,
                   threshold_deg: float, count_weight: float, iterations: int) -> np.ndarray:
    """Best position [mm] of the vertex: steps ``dirs`` (D, 3) halving from min(½ edge, radius)
    down to 0.02 edge, plus the move ½ P (ideal − x) towards ``ideal``, each within ``radius``
    of x0; a step is kept only when it raises :func:`star_score`."""
    x = x0.copy()
    best = star_score(star_pts, slot, x, threshold_deg, count_weight)
    step = min(0.5 * edge, radius)
    cand = np.empty(3)
    pick = np.empty(3)
    for _ in range(iterations):
        top = -np.inf
        for d in range(dirs.shape[0] + 1):
            for c in range(3):
                if d < dirs.shape[0]:
                    cand[c] = x[c] + step * dirs[d, c]
                else:
                    cand[c] = x[c] + 0.5 * (projector[c, 0] * (ideal[0] - x[0])
                                            + projector[c, 1] * (ideal[1] - x[1])
                                            + projector[c, 2] * (ideal[2] - x[2]))
            if math.sqrt((cand[0] - x0[0]) ** 2 + (cand[1] - x0[1]) ** 2
                         + (cand[2] - x0[2]) ** 2) > radius:
                continue
            score = star_score(star_pts, slot, cand, threshold_deg, count_weight)
            if score > top:
                top = score
                pick[:] = cand
        if top > best:
            best = top
            x[:] = pick
        else:
            step *= 0.5
            if step < 0.02 * edge:
                break
    return x


@njit(cache=True)
def min_dihedral_vol6(points_mm: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(smallest dihedral angle [°], 6 × signed volume [mm³]) of each tetrahedron (M, 4)."""
    angle = np.empty(tets.shape[0])
    vol6 = np.empty(tets.shape[0])
    q = np.empty((4, 3))
    for t in range(tets.shape[0]):
        for k in range(4):
            for c in range(3):
                q[k, c] = points_mm[tets[t, k], c]
        angle[t], vol6[t] = tet_min_dihedral_vol6(q)
    return angle, vol6
