"""njit volume sources: particles born uniformly per unit mass in a region, isotropic.

Source v is chosen with probability w_v/Σw (``src_cdf``), its energy from its spectrum lines
(``spec_cdf``), a cell of its region with probability m_c/Σm (``cell_cdf``, masses in g: a tet's
mass Vol·ρ̄, a voxel's mass outside the mesh), then a point in the cell with density ∝ ρ:

- **tet** with vertex densities ρ_i and linear ρ = Σλ_iρ_i (λ barycentric): the density
  ∝ Σ_i ρ_i λ_i is the mixture over i, with weights ρ_i/Σρ (each ∫λ_i dV = V/4), of the
  densities ∝ λ_i, which are Dirichlet(α) laws of λ with α_i = 2 and the other α_j = 1. So: pick
  vertex i by ρ_i, draw Gamma(α_j) variates g_j (g = −ln ξ for α = 1, −ln ξξ' for α = 2),
  λ = g/Σg, point = Σλ_j p_j. Exact, no rejection (Devroye, "Non-uniform random variate
  generation", 1986, ch. XI.4: Dirichlet by normalised gammas).
- **voxel** (constant density): uniform in the box; in a voxel the mesh surface cuts (hybrid
  worlds: its material is flagged −m − 1), a point inside the mesh belongs to the mesh's mass,
  so it is rejected and drawn again in the same voxel (the voxel's mass counts only its part
  outside the mesh, so the accepted points are uniform per unit mass there).

The direction is isotropic. Positions are in the world's frame (the grid frame of a hybrid or
voxel world).
"""

import math
from typing import NamedTuple

from tetdose._jit import kernel
from tetdose._random import next_uniform
from tetdose._typing import FloatArray, IntArray
from tetdose.transport.geometry._world import start_cell, voxel_ijk
from tetdose.transport.physics._photon import isotropic_direction

#: Points drawn in one voxel before the last one is kept (a voxel almost wholly inside the mesh
#: has almost no mass and is almost never chosen).
MAX_VOXEL_DRAWS = 1000


class VolumeArrays(NamedTuple):
    """Volume sources as flat arrays (kernel cell ids, masses [g], points [mm], energies [MeV])."""

    src_cdf: FloatArray  # (V,) cumulative source probability
    particle: IntArray  # (V,) species: 0 e⁻, 1 e⁺, 2 photon
    spec_start: IntArray  # (V + 1,) offsets into spec_energy / spec_cdf
    spec_energy: FloatArray  # (K,) line energies [MeV]
    spec_cdf: FloatArray  # (K,) cumulative line probability within each source
    cell_start: IntArray  # (V + 1,) offsets into cell / cell_cdf
    cell: IntArray  # (S,) global kernel cell ids of each source's region
    cell_cdf: FloatArray  # (S,) cumulative mass fraction within each source
    tets: IntArray  # (M, 4) vertex ids of each kernel tet
    points: FloatArray  # (N, 3) mesh vertices in the world frame [mm]
    point_density: FloatArray  # (N,) vertex densities [g/cm³]


@kernel
def _search(cdf, lo, hi, xi):
    """First index in [lo, hi) with cdf[index] > xi (hi − 1 if none): binary search."""
    hi -= 1
    while lo < hi:
        mid = (lo + hi) // 2
        if cdf[mid] > xi:
            hi = mid
        else:
            lo = mid + 1
    return lo


@kernel
def _point_in_tet(vol, k, state):
    """(state, x, y, z): a point of tet ``k`` with density ∝ the linear ρ (module docstring)."""
    t = vol.tets[k]
    r0, r1 = vol.point_density[t[0]], vol.point_density[t[1]]
    r2, r3 = vol.point_density[t[2]], vol.point_density[t[3]]
    total = r0 + r1 + r2 + r3
    state, xi = next_uniform(state)
    xi *= total
    state, a0 = next_uniform(state)
    state, a1 = next_uniform(state)
    state, a2 = next_uniform(state)
    state, a3 = next_uniform(state)
    state, b = next_uniform(state)
    g0, g1, g2, g3 = -math.log(1.0 - a0), -math.log(1.0 - a1), -math.log(1.0 - a2), -math.log(1.0 - a3)
    extra = -math.log(1.0 - b)  # Gamma(2) = Gamma(1) + Gamma(1) for the vertex drawn by ρ_i
    if xi < r0:
        g0 += extra
    elif xi < r0 + r1:
        g1 += extra
    elif xi < r0 + r1 + r2:
        g2 += extra
    else:
        g3 += extra
    g_sum = g0 + g1 + g2 + g3
    p0, p1, p2, p3 = vol.points[t[0]], vol.points[t[1]], vol.points[t[2]], vol.points[t[3]]
    x = g0 * p0[0] + g1 * p1[0] + g2 * p2[0] + g3 * p3[0]
    y = g0 * p0[1] + g1 * p1[1] + g2 * p2[1] + g3 * p3[1]
    z = g0 * p0[2] + g1 * p1[2] + g2 * p2[2] + g3 * p3[2]
    return state, x / g_sum, y / g_sum, z / g_sum


@kernel
def _point_in_voxel(wg, vid, state):
    """(state, x, y, z): a point uniform in voxel ``vid`` outside the mesh (module docstring)."""
    g = wg.vox
    i, j, k = voxel_ijk(g, vid)
    m_tets = wg.tet.planes.shape[0]
    x = y = z = 0.0
    for _ in range(MAX_VOXEL_DRAWS):
        state, a = next_uniform(state)
        state, b = next_uniform(state)
        state, c = next_uniform(state)
        x = g.lo[0] + (i + a) * g.cell[0]
        y = g.lo[1] + (j + b) * g.cell[1]
        z = g.lo[2] + (k + c) * g.cell[2]
        if g.material[vid] >= 0:
            break
        cell, _x, _y, _z, _n = start_cell(wg, x, y, z, 0.0, 0.0, 1.0)
        if cell >= m_tets or cell < 0:
            break
    return state, x, y, z


@kernel
def sample_volume(wg, vol, state):
    """(state, species, energy [MeV], global cell, x, y, z, u, v, w) of one volume-source
    particle (module docstring)."""
    n_src = vol.src_cdf.shape[0]
    state, xi = next_uniform(state)
    s = _search(vol.src_cdf, 0, n_src, xi)
    state, xi = next_uniform(state)
    e = vol.spec_energy[_search(vol.spec_cdf, vol.spec_start[s], vol.spec_start[s + 1], xi)]
    state, xi = next_uniform(state)
    cell = vol.cell[_search(vol.cell_cdf, vol.cell_start[s], vol.cell_start[s + 1], xi)]
    m_tets = wg.tet.planes.shape[0]
    if cell < m_tets:
        state, x, y, z = _point_in_tet(vol, cell, state)
    else:
        state, x, y, z = _point_in_voxel(wg, cell - m_tets, state)
    state, u, v, w = isotropic_direction(state)
    return state, vol.particle[s], e, cell, x, y, z, u, v, w
