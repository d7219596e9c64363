"""The paper's hit-and-miss estimate of tetrahedron ∩ voxel fractions (eq. 7), numba kernel.

F_kj = N_j / N_R with N_R points drawn uniformly in the tetrahedron (Rocchini & Cignoni,
"Generating random points in a tetrahedron", J. Graphics Tools 5(4), 2000), one counter-based
random stream per tetrahedron; the output layout is that of
:func:`tetdose.core._overlap_kernels.overlap_exact`. Kept as the paper's reference method.
"""

import math

import numpy as np
from numba import njit, prange

from tetdose._jit import kernel
from tetdose._random import next_uniform, seed_for


@njit(cache=True, parallel=True)
def overlap_monte_carlo(points_u, tets, nx, ny, nz, n_samples, seed, offsets, voxel_out,
                        vol_out, cen_out, out_count):
    """Hit-and-miss estimate (paper eq. 7): F_kj = N_j / N_R with N_R uniform points per tet.

    Same layout as :func:`overlap_exact`; ``vol_out`` holds F_kj · Vol(T_k) and ``cen_out`` the
    mean position of the points that fell in voxel j. Points outside the grid are dropped.
    """
    n_tets = tets.shape[0]
    for k in prange(n_tets):
        state = seed_for(seed, 1, k)
        ids = np.empty(n_samples, dtype=np.int64)
        pts = np.empty((n_samples, 3))
        a = points_u[tets[k, 0]]
        e1 = points_u[tets[k, 1]] - a
        e2 = points_u[tets[k, 2]] - a
        e3 = points_u[tets[k, 3]] - a
        vol = abs(e1[0] * (e2[1] * e3[2] - e2[2] * e3[1]) - e1[1] * (e2[0] * e3[2] - e2[2] * e3[0])
                  + e1[2] * (e2[0] * e3[1] - e2[1] * e3[0])) / 6.0
        for r in range(n_samples):
            state, s = next_uniform(state)
            state, t = next_uniform(state)
            state, u = next_uniform(state)
            s, t, u = _fold_into_tet(s, t, u)
            for d in range(3):
                pts[r, d] = a[d] + s * e1[d] + t * e2[d] + u * e3[d]
            i = int(math.floor(pts[r, 0] + 0.5))
            j = int(math.floor(pts[r, 1] + 0.5))
            kk = int(math.floor(pts[r, 2] + 0.5))
            inside = 0 <= i < nx and 0 <= j < ny and 0 <= kk < nz
            ids[r] = ((kk * ny + j) * nx + i) if inside else -1
        order = np.argsort(ids, kind="mergesort")
        written = 0
        r = 0
        while r < n_samples:
            vid = ids[order[r]]
            count = 0
            c0 = 0.0
            c1 = 0.0
            c2 = 0.0
            while r < n_samples and ids[order[r]] == vid:
                c0 += pts[order[r], 0]
                c1 += pts[order[r], 1]
                c2 += pts[order[r], 2]
                count += 1
                r += 1
            if vid >= 0:
                w = offsets[k] + written
                voxel_out[w] = vid
                vol_out[w] = vol * count / n_samples
                cen_out[w, 0] = c0 / count
                cen_out[w, 1] = c1 / count
                cen_out[w, 2] = c2 / count
                written += 1
        out_count[k] = written


@kernel
def _fold_into_tet(s, t, u):
    """Map a uniform point of the unit cube to a uniform point of the unit corner tetrahedron."""
    if s + t > 1.0:
        s, t = 1.0 - s, 1.0 - t
    if t + u > 1.0:
        t, u = 1.0 - u, 1.0 - s - t
    elif s + t + u > 1.0:
        s, u = 1.0 - t - u, s + t + u - 1.0
    return s, t, u
