"""Dose on the mesh vertices: the mass-weighted L2 projection of the tets' dose onto the linear basis.

The density lives on the vertices, linear in each tet (the paper's representation); the dose can
live there too. With φ_i the hat function of vertex i (the barycentric coordinate λ_i in each of
its tets) and ρ = Σ_a ρ_a φ_a the density [g/cm³], the vertex dose d [Gy] solves

    M_ρ d = b,     (M_ρ)_ij = ∫ ρ φ_i φ_j dV,     b_i = ∫ e φ_i dV,

with e the energy deposited per volume: the d whose field Σ d_i φ_i is closest to the dose in the
mass-weighted norm ∫ ρ (·)² dV. Per tet k (volume V_k, ∫ λ_i λ_j λ_l dV = V_k · 3! a!b!c!d! / 6!
for exponents a…d of the four λ):

    (M_k)_ij = V_k Σ_l ρ_l c_ijl,   c = 1/20 (i = j = l), 1/60 (two equal), 1/120 (all differ).

The transport scores the energy E_k of each tet, not where in the tet it was deposited, so b is
taken with the dose D_k = E_k / m_k constant in tet k and the energy density ∝ ρ (the exact
per-tet formula for that model, not the lumped Σ_k E_k/4):

    b_i = Σ_k D_k ∫_k ρ φ_i dV = Σ_k D_k V_k (ρ_i + Σ_a ρ_a) / 20.

It keeps the energy: ∫ ρ Σ_i d_i φ_i dV = Σ_i b_i = Σ_k E_k (Σ_j (M_ρ)_ij = ∫ ρ φ_i), and a
uniform dose stays exactly uniform. σ: the projection is linear, so every batch's dose is
projected and the spread of the batch solutions gives σ as for the tets
(:mod:`tetdose.transport.history.result`). Solved by conjugate gradients with the diagonal as
preconditioner (a mass matrix: a few tens of iterations whatever the mesh size; A. J. Wathen,
"Realistic eigenvalue bounds for the Galerkin mass matrix", IMA J. Numer. Anal. 7 (1987) 449).
Vertices of zero mass (only density-0 tets around them) get dose 0.

Near a dose gradient the projection mixes the tets around a vertex (about two tet layers): a
penumbra is smoothed by about the tet size, and noise is averaged over the vertex's tets — the
bias and the variance gain are measured in tests/unit/test_vertex_dose.py and
bench/bench_precision.py.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import LinearOperator, cg

from tetdose._constants import G_PER_KG, J_PER_MEV, MM3_PER_CM3
from tetdose._typing import FloatArray
from tetdose.core.mass import tet_mass_g
from tetdose.core.mesh import TetMesh
from tetdose.errors import GeometryMismatchError
from tetdose.transport.history.result import DoseResult

#: Relative residual of the CG solves.
CG_RTOL = 1e-12
#: ∫ λ_i λ_j λ_l dV / V for (i, j, l) all equal, two equal, all different.
_C3 = (1.0 / 20.0, 1.0 / 60.0, 1.0 / 120.0)


def mass_matrix(mesh: TetMesh, density_g_cm3: FloatArray) -> sp.csr_matrix:
    """(N, N) M_ρ [g] of the mesh's hat functions with the linear density (module docstring)."""
    rho = np.asarray(density_g_cm3, dtype=np.float64)[mesh.tets]  # (M, 4)
    vol = mesh.volumes_mm3 / MM3_PER_CM3
    total = rho.sum(axis=1)
    blocks = np.empty((mesh.n_tets, 4, 4))
    for i in range(4):
        for j in range(4):
            if i == j:  # Σ_l ρ_l c_iil = ρ_i/20 + (Σρ − ρ_i)/60
                blocks[:, i, j] = rho[:, i] * _C3[0] + (total - rho[:, i]) * _C3[1]
            else:  # (ρ_i + ρ_j)/60 + (Σρ − ρ_i − ρ_j)/120
                s = rho[:, i] + rho[:, j]
                blocks[:, i, j] = s * _C3[1] + (total - s) * _C3[2]
    blocks *= vol[:, None, None]
    rows = np.repeat(mesh.tets, 4, axis=1).ravel()
    cols = np.tile(mesh.tets, (1, 4)).ravel()
    return sp.csr_matrix((blocks.ravel(), (rows, cols)), shape=(mesh.n_points,) * 2)


def load_matrix(mesh: TetMesh, density_g_cm3: FloatArray) -> sp.csr_matrix:
    """(N, M) L [g] with b = L D for per-tet doses D: L_ik = V_k (ρ_i + Σ_a ρ_a) / 20."""
    rho = np.asarray(density_g_cm3, dtype=np.float64)[mesh.tets]
    w = (rho + rho.sum(axis=1, keepdims=True)) / 20.0 * (mesh.volumes_mm3 / MM3_PER_CM3)[:, None]
    cols = np.repeat(np.arange(mesh.n_tets), 4)
    return sp.csr_matrix((w.ravel(), (mesh.tets.ravel(), cols)), shape=(mesh.n_points, mesh.n_tets))


def project(mesh: TetMesh, tet_dose_gy: FloatArray, density_g_cm3: FloatArray | None = None
            ) -> FloatArray:
    """Vertex dose [Gy] of per-tet doses ``tet_dose_gy`` ((M,) or (M, K) for K fields at once)."""
    rho = _density(mesh, density_g_cm3)
    m = mass_matrix(mesh, rho)
    rhs = load_matrix(mesh, rho) @ np.asarray(tet_dose_gy, dtype=np.float64)
    return _solve(m, rhs)


def vertex_dose(mesh: TetMesh, result: DoseResult) -> tuple[FloatArray, FloatArray]:
    """(dose, σ) [Gy] on the vertices of ``mesh`` from a run on it (the mesh part of a hybrid
    run): the projection of the run's per-tet dose and the batch spread of the projected batch
    doses (module docstring)."""
    part = result.mesh_part()
    if part.n_tets != mesh.n_tets:
        raise GeometryMismatchError(f"the result has {part.n_tets} tetrahedra, the mesh "
                                    f"{mesh.n_tets}; pass the mesh the dose was computed on")
    kg = part.mass_g / G_PER_KG
    gy = np.divide(part.particles * J_PER_MEV, kg, out=np.zeros_like(kg), where=kg > 0)
    x = part.energy_per_batch_mev / part.histories_per_batch[:, None] * gy  # (B, M) batch doses
    fields = np.column_stack([part.dose_gy, x.T])
    solved = project(mesh, fields)
    b = part.n_batches
    dev = solved[:, 1:] - solved[:, 1:].mean(axis=1, keepdims=True)
    return solved[:, 0], np.sqrt((dev**2).sum(axis=1) / (b * (b - 1)))


def with_vertex_dose(mesh: TetMesh, result: DoseResult) -> TetMesh:
    """``mesh`` with point_data ``dose_vertex`` and ``dose_vertex_std`` [Gy]."""
    d, s = vertex_dose(mesh, result)
    return mesh.with_data(point_data={"dose_vertex": d, "dose_vertex_std": s})


def _density(mesh: TetMesh, density_g_cm3: FloatArray | None) -> FloatArray:
    tet_mass_g(mesh, density_g_cm3)  # refuses a mesh without (or with a wrong) density
    return np.asarray(mesh.point_data["density"] if density_g_cm3 is None else density_g_cm3,
                      dtype=np.float64)


def _solve(m: sp.csr_matrix, rhs: FloatArray) -> FloatArray:
    diag = m.diagonal()
    live = diag > 0
    inv = np.divide(1.0, diag, out=np.zeros_like(diag), where=live)
    mm = (m + sp.diags(np.where(live, 0.0, 1.0))).tocsr()  # massless vertices: d = 0
    pre = LinearOperator(m.shape, matvec=lambda v: inv * np.ravel(v) + np.where(live, 0.0,
                                                                                  np.ravel(v)))
    cols = rhs.reshape(len(diag), -1)
    out = np.zeros_like(cols)
    for k in range(cols.shape[1]):
        r = np.where(live, cols[:, k], 0.0)
        if np.any(r):
            out[:, k], info = cg(mm, r, rtol=CG_RTOL, atol=0.0, M=pre, maxiter=10 * len(diag))
            if info != 0:
                raise ArithmeticError(f"the vertex-dose projection did not converge ({info})")
    return out.reshape(rhs.shape)
