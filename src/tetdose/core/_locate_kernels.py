"""Point location in a tetrahedral mesh through a uniform bucket grid (numba kernel).

For each point, the tetrahedra listed in its bucket are tried in order; the first whose
barycentric coordinates λ = T⁻¹(x − a), λ₀ = 1 − Σλ are all ≥ −tol contains it.
"""

import math

from numba import njit, prange


@njit(cache=True, parallel=True)
def locate(points, lo, h, n, ptr, bucket_tets, inv, origin, tol, tet_out, bary_out):
    """points (P, 3) [mm]; lo (3,), h bucket size [mm], n (3,) bucket counts; ptr/bucket_tets the
    bucket → tet lists (CSR); inv (M, 3, 3) inverse edge matrices; origin (M, 3) first vertices.
    Writes tet_out (P,) (−1 outside) and bary_out (P, 4)."""
    for p in prange(points.shape[0]):
        tet_out[p] = -1
        cell = 0
        inside = True
        for d in range(3):
            r = (points[p, d] - lo[d]) / h
            if r < -1e-9 or r > n[d] + 1e-9:
                inside = False
            c = min(max(int(math.floor(r)), 0), n[d] - 1)
            cell = cell * n[d] + c
        if not inside:
            continue
        for q in range(ptr[cell], ptr[cell + 1]):
            k = bucket_tets[q]
            d0 = points[p, 0] - origin[k, 0]
            d1 = points[p, 1] - origin[k, 1]
            d2 = points[p, 2] - origin[k, 2]
            l1 = inv[k, 0, 0] * d0 + inv[k, 0, 1] * d1 + inv[k, 0, 2] * d2
            l2 = inv[k, 1, 0] * d0 + inv[k, 1, 1] * d1 + inv[k, 1, 2] * d2
            l3 = inv[k, 2, 0] * d0 + inv[k, 2, 1] * d1 + inv[k, 2, 2] * d2
            l0 = 1.0 - l1 - l2 - l3
            if min(min(l0, l1), min(l2, l3)) >= -tol:
                tet_out[p] = k
                bary_out[p, 0] = l0
                bary_out[p, 1] = l1
                bary_out[p, 2] = l2
                bary_out[p, 3] = l3
                break
