"""Dose accumulated over breathing phases: on the mesh, and the two voxel ways for comparison.

**On the mesh.** Every phase has the same tetrahedra, and a tetrahedron is a material volume:
the matter in tet k is the same in every phase. Energy deposited in tet k is therefore
deposited in the same matter, and the accumulated dose is the energy over the mass,

    D_k = Σ_p w_p E_{k,p} / Σ_p w_p m_{k,p},   E_{k,p} = D_{k,p} m_{k,p},   Σ_p w_p = 1,

with w_p the phase time weights: no dose warping or energy mapping is needed. With a
mass-conserving density update m_{k,p} = m_k and this is Σ_p w_p E_{k,p} / m_k. The P1 density
re-solved per phase (:mod:`tetdose.motion.conserve`) keeps the total mass exactly but each
tet's mass only up to the projection error (eq. 10 is one equation per tet for one unknown per
vertex: overdetermined), ≈ 1 % under breathing and up to ≈ 5 % where a tet's volume changes by a
third; :func:`phase_mass_spread` reports it. What must hold is the total mass of each phase
(exact with the L2 update): a phase whose total differs by more than :data:`MASS_RTOL` had its
densities never updated for the motion, and is refused. The statistical
uncertainty of independent phase runs adds as σ_k² = Σ_p w_p² (σ_{k,p} m_{k,p})² / m̄_k².

**On voxels** (the usual 4D-CT practice), with the motion taken from the mesh itself so that the
methods differ only by method. A reference point x inside the reference mesh, in tet k with
barycentric coordinates λ, moves in phase p to φ_p(x) = Σ_a λ_a x_{p,a} (the mesh's piecewise
linear motion); outside the mesh nothing moves.

(a) Direct dose mapping: D(x_j) = Σ_p w_p D_p(φ_p(x_j)) at each reference voxel centre x_j,
    D_p trilinear (dose interpolated through the displacement field).
(b) Energy/mass transfer mapping (Siebers & Zhong, Med. Phys. 35 (2008) 1096; matRad's
    EMT): each phase voxel is split into s³ sub-voxels carrying energy D_pi m_pi / s³ and mass
    m_pi / s³; each sub-voxel centre y is pulled back with φ_p⁻¹ (located in the phase mesh,
    mapped with the same barycentric coordinates onto the reference vertices) and deposited in
    the reference voxel containing it; D_j = Σ_p w_p E_pj / Σ_p w_p M_pj.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from tetdose._constants import MM3_PER_CM3
from tetdose._typing import FloatArray
from tetdose.core.image import Image, ImageGrid
from tetdose.core.mass import tet_mass_g
from tetdose.core.mesh import TetMesh
from tetdose.core.transfer import interpolate_at_points, locate_points
from tetdose.errors import DensityError, OptionError, TopologyMismatchError

#: Largest relative difference of a phase's total mass from the phases' mean accepted by default
#: (the L2 update keeps it to 1e-15, the paper's least squares to ~1e-4; densities left
#: un-updated on moved points change it by the volume change, percents).
MASS_RTOL = 1e-3
#: Phase voxels handled per chunk in the energy/mass transfer.
EMT_CHUNK = 50_000


@dataclass(frozen=True, eq=False)
class AccumulatedDose:
    """Accumulated per-tet dose [Gy], its standard deviation [Gy], time-weighted tet masses [g],
    phase weights, and the largest relative spread of a tet's mass over the phases."""

    dose_gy: FloatArray
    dose_std_gy: FloatArray | None
    mass_g: FloatArray
    weights: FloatArray
    mass_spread_rel: float


def phase_weights(weights: FloatArray | None, n_phases: int) -> FloatArray:
    """Time weights normalised to sum 1 (default 1/K each)."""
    if weights is None:
        return np.full(n_phases, 1.0 / n_phases)
    w = np.asarray(weights, dtype=np.float64).reshape(-1)
    if len(w) != n_phases or np.any(w < 0) or w.sum() <= 0:
        raise OptionError(f"phase weights {w} are unusable: give {n_phases} non-negative "
                          "weights with a positive sum (one per phase)")
    return w / w.sum()


def phase_mass_spread(mass_g: FloatArray) -> float:
    """Largest relative spread (max − min) / mean of a tet's mass over the phases, (K, M) in g."""
    m = np.asarray(mass_g, dtype=np.float64)
    mean = m.mean(axis=0)
    rel = np.divide(m.max(axis=0) - m.min(axis=0), mean, out=np.zeros_like(mean),
                    where=mean > 0)
    return float(rel.max())


def check_phase_totals(mass_g: FloatArray, *, rtol: float = MASS_RTOL) -> None:
    """Raise :class:`DensityError` naming the phase whose total mass [g] differs by > ``rtol``."""
    m = np.asarray(mass_g, dtype=np.float64)
    if m.ndim != 2:
        raise TopologyMismatchError(f"masses must have shape (phases, tets), got {m.shape}")
    total = m.sum(axis=1)
    rel = np.abs(total - total.mean()) / total.mean()
    p = int(np.argmax(rel))
    if rel[p] > rtol:
        raise DensityError(
            f"phase {p} holds {total[p]:.9g} g, the phases {total.mean():.9g} g on average "
            f"(relative {rel[p]:.3g} > {rtol:g}); the matter must be the same in every phase: "
            "update the phase densities with tetdose.motion.conserve (tetdose deform) first")


def accumulate_mesh_dose(dose_gy: FloatArray, mass_g: FloatArray, *,
                         weights: FloatArray | None = None, dose_std_gy: FloatArray | None = None,
                         rtol: float = MASS_RTOL) -> AccumulatedDose:
    """D_k = Σ_p w_p D_{k,p} m_{k,p} / Σ_p w_p m_{k,p} from (K, M) doses [Gy] and masses [g]."""
    d = np.asarray(dose_gy, dtype=np.float64)
    m = np.asarray(mass_g, dtype=np.float64)
    if d.shape != m.shape:
        raise TopologyMismatchError(f"doses {d.shape} and masses {m.shape} must both be "
                                    "(phases, tets) for one mesh topology")
    check_phase_totals(m, rtol=rtol)
    w = phase_weights(weights, len(d))
    energy = np.einsum("p,pk->k", w, d * m)
    mass = np.einsum("p,pk->k", w, m)
    dose = np.divide(energy, mass, out=np.zeros_like(mass), where=mass > 0)
    std = None
    if dose_std_gy is not None:
        s = np.asarray(dose_std_gy, dtype=np.float64).reshape(d.shape)
        var = np.einsum("p,pk->k", w**2, (s * m) ** 2)
        std = np.divide(np.sqrt(var), mass, out=np.zeros_like(mass), where=mass > 0)
    return AccumulatedDose(dose, std, mass, w, phase_mass_spread(m))


def accumulate_meshes(phases: Sequence[TetMesh], dose_gy: Sequence[FloatArray], *,
                      weights: FloatArray | None = None,
                      dose_std_gy: Sequence[FloatArray] | None = None,
                      rtol: float = MASS_RTOL) -> AccumulatedDose:
    """:func:`accumulate_mesh_dose` for phase meshes carrying point_data ``density`` [g/cm³]."""
    for mesh in phases[1:]:
        phases[0].same_topology(mesh)
    mass = np.stack([tet_mass_g(mesh) for mesh in phases])
    std = None if dose_std_gy is None else np.stack(dose_std_gy)
    return accumulate_mesh_dose(np.stack(dose_gy), mass, weights=weights, dose_std_gy=std,
                                rtol=rtol)


def accumulate_static_voxels(dose_gy: Sequence[FloatArray], mass_g: Sequence[FloatArray], *,
                             weights: FloatArray | None = None,
                             dose_std_gy: Sequence[FloatArray] | None = None
                             ) -> tuple[FloatArray, FloatArray | None, FloatArray]:
    """(dose, σ, mass) of voxels that do not move: D_j = Σ_p w_p D_pj m_pj / Σ_p w_p m_pj [Gy].

    The voxel part of a hybrid 4D run on a static body (the reference CT outside the mesh): a
    voxel's mass m_pj changes only as much of it as the moving mesh covers in phase p.
    """
    d, m = np.stack(dose_gy), np.stack(mass_g)
    w = phase_weights(weights, len(d))
    mass = np.einsum("p,pj->j", w, m)
    dose = np.divide(np.einsum("p,pj->j", w, d * m), mass, out=np.zeros_like(mass),
                     where=mass > 0)
    std = None
    if dose_std_gy is not None:
        var = np.einsum("p,pj->j", w**2, (np.stack(dose_std_gy) * m) ** 2)
        std = np.divide(np.sqrt(var), mass, out=np.zeros_like(mass), where=mass > 0)
    return dose, std, mass


def moved_points(reference: TetMesh, phase_points_mm: FloatArray, points_mm: FloatArray
                 ) -> FloatArray:
    """φ_p(x): reference points [mm] carried by the mesh motion to phase p (identity outside)."""
    return _carry(reference, np.asarray(phase_points_mm, dtype=np.float64), points_mm)


def _carry(source: TetMesh, target_points_mm: FloatArray, points_mm: FloatArray) -> FloatArray:
    """Points located in ``source`` and mapped with their barycentric coordinates onto the
    same vertices at ``target_points_mm``; points outside ``source`` stay put."""
    if target_points_mm.shape != source.points_mm.shape:
        raise TopologyMismatchError(f"phase points {target_points_mm.shape} do not match the "
                                    f"mesh's {source.points_mm.shape}")
    pts = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
    tet, bary = locate_points(source, pts)
    inside = tet >= 0
    out = pts.copy()
    corners = target_points_mm[source.tets[tet[inside]]]  # (P, 4, 3)
    out[inside] = np.einsum("pa,pad->pd", bary[inside], corners)
    return out


def direct_dose_mapping(reference: TetMesh, phase_points_mm: FloatArray,
                        phase_dose: Sequence[Image], grid: ImageGrid, *,
                        weights: FloatArray | None = None) -> Image:
    """(a) D(x_j) = Σ_p w_p D_p(φ_p(x_j)) on ``grid`` (0 where φ_p(x_j) leaves the phase image)."""
    pts = np.asarray(phase_points_mm, dtype=np.float64)
    w = phase_weights(weights, len(phase_dose))
    if len(pts) != len(phase_dose):
        raise OptionError(f"{len(pts)} phase point sets for {len(phase_dose)} phase doses: "
                          "give one dose image per phase")
    centres = grid.voxel_centers_mm()
    total = np.zeros(grid.n_voxels)
    for p, dose in enumerate(phase_dose):
        moved = moved_points(reference, pts[p], centres)
        total += w[p] * interpolate_at_points(dose, moved, outside=0.0)
    return Image(total.reshape(grid.shape), grid)


def energy_mass_transfer(reference: TetMesh, phase_points_mm: FloatArray,
                         phase_dose: Sequence[Image], phase_density_g_cm3: Sequence[Image],
                         grid: ImageGrid, *, weights: FloatArray | None = None,
                         subdivisions: int = 2) -> Image:
    """(b) D_j = Σ_p w_p E_pj / Σ_p w_p M_pj by sub-voxel energy and mass transfer (module doc)."""
    pts = np.asarray(phase_points_mm, dtype=np.float64)
    w = phase_weights(weights, len(phase_dose))
    if not len(pts) == len(phase_dose) == len(phase_density_g_cm3):
        raise OptionError(f"{len(pts)} phase point sets, {len(phase_dose)} doses and "
                          f"{len(phase_density_g_cm3)} density images: give one of each per phase")
    if subdivisions < 1:
        raise OptionError(f"subdivisions must be an integer ≥ 1, got {subdivisions}; "
                          "use 2 (8 sub-voxels per voxel) or more")
    energy = np.zeros(grid.n_voxels)
    mass = np.zeros(grid.n_voxels)
    for p, (dose, rho) in enumerate(zip(phase_dose, phase_density_g_cm3, strict=True)):
        dose.grid.require_same(rho.grid, f"phase {p} dose and density images")
        phase_mesh = reference.moved(pts[p])
        m_vox = np.asarray(rho.array, dtype=np.float64).ravel() * (
            dose.grid.voxel_volume_mm3 / MM3_PER_CM3)
        d_vox = np.asarray(dose.array, dtype=np.float64).ravel()
        moving = _voxels_near_box(dose.grid, phase_mesh.bounds_mm())
        if dose.grid.same_as(grid):  # voxels away from the mesh do not move: transfer in place
            still = ~moving
            energy[still] += w[p] * d_vox[still] * m_vox[still]
            mass[still] += w[p] * m_vox[still]
            candidates = np.flatnonzero(moving)
        else:
            candidates = np.arange(dose.grid.n_voxels)
        for lo in range(0, len(candidates), EMT_CHUNK):
            ids = candidates[lo:lo + EMT_CHUNK]
            sub = _sub_voxel_centres(dose.grid, ids, subdivisions)
            back = _carry(phase_mesh, reference.points_mm, sub)
            target = grid.voxel_of(back)
            ok = target >= 0
            src = np.repeat(ids, subdivisions**3)[ok]
            frac = w[p] / subdivisions**3
            energy += np.bincount(target[ok], weights=frac * d_vox[src] * m_vox[src],
                                  minlength=grid.n_voxels)
            mass += np.bincount(target[ok], weights=frac * m_vox[src], minlength=grid.n_voxels)
    dose_gy = np.divide(energy, mass, out=np.zeros_like(energy), where=mass > 0)
    return Image(dose_gy.reshape(grid.shape), grid)


def _voxels_near_box(grid: ImageGrid, box_mm: tuple[FloatArray, FloatArray]) -> np.ndarray:
    """(n_voxels,) True for voxels that may overlap the axis-aligned box (centre within half a
    voxel diagonal of it); the others lie wholly outside the mesh and do not move."""
    lo, hi = box_mm
    half_diag = 0.5 * float(np.linalg.norm(grid.spacing_mm))
    c = grid.voxel_centers_mm()
    return np.all((c >= lo - half_diag) & (c <= hi + half_diag), axis=1)


def _sub_voxel_centres(grid: ImageGrid, ids: np.ndarray, s: int) -> FloatArray:
    """Centres [mm] of the s³ sub-voxels of each voxel in ``ids`` (voxel-major order)."""
    k, j, i = np.unravel_index(ids, grid.shape)
    base = np.stack([i, j, k], axis=1).astype(np.float64)
    t = (np.arange(s) + 0.5) / s - 0.5
    sub = np.stack(np.meshgrid(t, t, t, indexing="ij"), axis=-1).reshape(-1, 3)
    return grid.index_to_physical((base[:, None, :] + sub[None, :, :]).reshape(-1, 3))

