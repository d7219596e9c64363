"""Per-phase vertex density with every tetrahedron keeping its reference mass (paper eq. 10–13).

Each phase is updated **from the reference phase** (never phase to phase), so no error
accumulates over a cycle. Two methods:

``"l2"`` (default, exactly mass conserving). Inside tetrahedron k the motion is affine,
x = χ(X), with constant Jacobian J_k = V_k(t)/V_k(0). Mass conservation per tetrahedron (indeed
per point) gives the pushed-forward density ρ_t(x) = ρ_0(X) · V_k(0)/V_k(t). Its L2 projection
onto the P1 space of the phase mesh solves M_t ρ = b with

    b_a = ∫_{Ω_t} ρ_t φ^t_a dx = Σ_k ∫_{T_k(t)} ρ_0(χ⁻¹x) V_k(0)/V_k(t) φ^t_a(x) dx
        = Σ_k ∫_{T_k(0)} ρ_0(X) φ^0_a(X) dX = (M_0 ρ_0)_a,

using dx = J_k dX and φ^t_a ∘ χ = φ^0_a (P1 basis functions are carried by the affine map).
So the right-hand side is the reference mass matrix times the reference density, whatever the
phase: ρ_t = project_l2(phase mesh, M_0 ρ_0). Since Σ_a φ_a = 1, the phase mass Σ_a ρ_a ∫φ^t_a
equals Σ_a b_a = ∫ρ_0: the total mass is the reference mass to round-off (the non-negativity
step of ``project_l2`` keeps that total). Uniform scaling by s gives M_t = s³M_0, ρ_t = ρ_0/s³;
a rigid motion gives M_t = M_0, ρ_t = ρ_0.

``"lsq"`` (the paper's eq. 12–13). d_k(t) = m_k(0)/V_k(t) with m_k(0) = V_k(0)·¼Σ_{a∈k} ρ_0(a),
then the least squares A·X(t) = d(t) of the mapping step (``solve_lsq``). Not volume weighted,
so the mesh mass is only approximately kept. Solved as X = X̃ + argmin‖A δ − (d − A X̃)‖ from the
warm start X̃_a = ρ_0(a)·∫φ^0_a/∫φ^t_a (the same minimiser, A having full column rank).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tetdose._checks import check_density
from tetdose._constants import MM3_PER_CM3
from tetdose._typing import FloatArray
from tetdose.core.mesh import TetMesh
from tetdose.errors import MeshError, TetdoseError
from tetdose.mapping.solve import (
    SOLVERS,
    lumped_mass_mm3,
    p1_mass_matrix_mm3,
    project_l2,
    solve_lsq,
    vertex_average_matrix,
)
from tetdose.motion.phases import DENSITY, PhaseSeries

#: Density update methods: the mapping's solvers (one spelling, :data:`tetdose.mapping.solve.SOLVERS`).
METHODS = SOLVERS


@dataclass(frozen=True)
class RegionVolume:
    """Volume change of one region in one phase: ΔV/V = V(t)/V(0) − 1 of its tets (min,
    median, max) and of the region as a whole (``total``)."""

    region: int
    n_tets: int
    min: float
    median: float
    max: float
    total: float

    def line(self) -> str:
        return (f"region {self.region}: ΔV/V {self.total:+.2%} in all (tets {self.min:+.1%} … "
                f"median {self.median:+.1%} … {self.max:+.1%})")


@dataclass(frozen=True)
class PhaseReport:
    """Mass and density summary of one phase, and the volume change of each region."""

    phase_percent: float
    total_mass_g: float
    mass_change_rel: float  # (m_t − m_0)/m_0
    min_density_g_cm3: float
    max_density_g_cm3: float
    worst_volume_change: float  # max_k |V_k(t)/V_k(0) − 1|
    regions: tuple[RegionVolume, ...] = ()

    def line(self) -> str:
        head = (f"phase {self.phase_percent:5.1f} %: mass {self.total_mass_g:.9g} g "
                f"(Δ {self.mass_change_rel:+.2e}), density {self.min_density_g_cm3:.4g}…"
                f"{self.max_density_g_cm3:.4g} g/cm³, worst |ΔV/V| {self.worst_volume_change:.3g}")
        return "\n".join([head] + ["    " + r.line() for r in self.regions])


def region_volumes(reference: TetMesh, phase: TetMesh) -> tuple[RegionVolume, ...]:
    """ΔV/V per region (one region 0 for an unlabelled mesh) of ``phase`` against ``reference``."""
    v0, v1 = reference.volumes_mm3, phase.volumes_mm3
    region = (np.zeros(reference.n_tets, dtype=np.int64) if reference.region is None
              else reference.region)
    out = []
    for label in np.unique(region):
        sel = region == label
        rel = v1[sel] / v0[sel] - 1.0
        out.append(RegionVolume(int(label), int(sel.sum()), float(rel.min()),
                                float(np.median(rel)), float(rel.max()),
                                float(v1[sel].sum() / v0[sel].sum() - 1.0)))
    return tuple(out)


def mesh_mass_g(mesh: TetMesh, density_g_cm3: FloatArray) -> float:
    """Mass of a P1 density field [g]: Σ_a ρ_a ∫φ_a dV / 1000 (paper eq. 22)."""
    return float(np.dot(lumped_mass_mm3(mesh), density_g_cm3)) / MM3_PER_CM3


def reference_density(mesh: TetMesh) -> FloatArray:
    """The reference vertex density (point_data ``density``) [g/cm³], checked finite and ≥ 0."""
    if DENSITY not in mesh.point_data:
        raise MeshError(f"the reference mesh has no point_data {DENSITY!r}; map a CT onto it "
                        "first (`tetdose map`)")
    rho = np.asarray(mesh.point_data[DENSITY], dtype=np.float64).reshape(-1)
    if len(rho) != mesh.n_points:
        raise MeshError(f"point_data {DENSITY!r} must hold one value per vertex")
    return check_density(rho, what="reference vertex densities",
                         fix="map the mesh again (`tetdose map`, default --solver l2)")


def update_density(reference: TetMesh, density0_g_cm3: FloatArray, phase: TetMesh, *,
                   method: str = "l2") -> FloatArray:
    """Vertex density [g/cm³] of ``phase`` keeping each reference tetrahedron's mass."""
    if method not in METHODS:
        raise TetdoseError(f"unknown density update method {method!r}; use one of {METHODS}")
    reference.same_topology(phase)
    rho0 = np.asarray(density0_g_cm3, dtype=np.float64)
    warm = rho0 * lumped_mass_mm3(reference) / lumped_mass_mm3(phase)
    if method == "l2":
        return project_l2(phase, p1_mass_matrix_mm3(reference) @ rho0, x0=warm)
    a = vertex_average_matrix(reference.tets, reference.n_points)
    d = (reference.volumes_mm3 * (a @ rho0)) / phase.volumes_mm3
    return warm + solve_lsq(phase, d - a @ warm)


def update_series(series: PhaseSeries, density0_g_cm3: FloatArray | None = None, *,
                  method: str = "l2") -> tuple[PhaseSeries, list[PhaseReport]]:
    """Density of every phase from the reference (default: its point_data ``density``).

    Parameters
    ----------
    series : PhaseSeries
        The reference mesh and the moved points of each phase [mm].
    density0_g_cm3 : (n_points,) float, optional
        Reference vertex densities [g/cm³]; default the reference mesh's point_data ``density``.
    method : {"l2", "lsq"}
        ``"l2"``: L2 projection of the pushed-forward density (total mass kept to round-off);
        ``"lsq"``: the paper's per-tetrahedron least squares (eq. 10).

    Returns
    -------
    series : PhaseSeries
        The same motion with point_data ``density`` [g/cm³] on every phase.
    reports : list of PhaseReport
        Per phase: mass [g], its relative change against the reference, density range [g/cm³]
        and the largest relative volume change of a tetrahedron.
    """
    ref = series.reference
    rho0 = reference_density(ref) if density0_g_cm3 is None else np.asarray(density0_g_cm3,
                                                                             dtype=np.float64)
    m0 = mesh_mass_g(ref, rho0)
    v0 = ref.volumes_mm3
    rhos, reports = [], []
    for k in range(series.n_phases):
        phase = ref.moved(series.points_mm[k])
        rho = update_density(ref, rho0, phase, method=method)
        mass = mesh_mass_g(phase, rho)
        rhos.append(rho)
        reports.append(PhaseReport(
            float(series.phase_percent[k]), mass, (mass - m0) / m0 if m0 else 0.0,
            float(rho.min()), float(rho.max()),
            float(np.abs(phase.volumes_mm3 / v0 - 1.0).max()), region_volumes(ref, phase)))
    return series.with_density(np.stack(rhos)), reports
