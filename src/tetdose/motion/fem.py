"""Surface-driven linear-elastic motion of a tetrahedral mesh (scikit-fem, optional extra).

The paper's §IV.A pipeline: the mesh's boundary surface is registered to a target surface of
the phase (rigid ICP, then closest-point displacements, :mod:`tetdose.motion.surface`) and the
boundary displacement is propagated into the volume by homogeneous isotropic linear
elasticity (paper eq. 18–20): find u with div σ(u) = 0, σ = λ tr(ε) I + 2μ ε,
ε = ½(∇u + ∇uᵀ), λ = Eν/((1+ν)(1−2ν)), μ = E/(2(1+ν)), and u = u_D on the Dirichlet set,
discretised with P1 tetrahedra (``ElementVectorH1(ElementTetP1())``) and solved with a sparse
direct solver. Defaults E = 7.8 kPa, ν = 0.45 (paper Table I). With displacement-only
boundary data the field does not depend on E; ν sets how the volume follows.

Large deformations: the boundary displacement is applied in ``n_increments`` equal steps, the
stiffness being re-assembled on the updated geometry each step (an updated-Lagrangian
sequence of linear solves); a rigid part found by ICP is applied exactly first (no strain).

This is the only module that builds scikit-fem objects (skfem's (3, N) layout stays here).
"""

from __future__ import annotations

import numpy as np

from tetdose._optional import import_optional
from tetdose._typing import BoolArray, FloatArray, IntArray
from tetdose.core.mesh import TetMesh, signed_volumes_mm3
from tetdose.errors import MeshError, TetdoseError
from tetdose.motion.surface import Surface, closest_points, icp

#: Liver elasticity of the paper's Table I: Young's modulus [kPa] and Poisson's ratio.
YOUNG_KPA = 7.8
POISSON = 0.45


def _skfem():  # noqa: ANN202 - module object
    skfem = import_optional("skfem", "fem", "FEM-driven motion")
    elasticity = import_optional("skfem.models.elasticity", "fem", "FEM-driven motion")
    return skfem, elasticity.lame_parameters, elasticity.linear_elasticity


def solve_linear_elastic(points_mm: FloatArray, tets: IntArray, fixed: BoolArray,
                         values_mm: FloatArray, *, young_kpa: float = YOUNG_KPA,
                         poisson: float = POISSON) -> FloatArray:
    """Displacement (N, 3) [mm] with u[fixed] = values_mm[fixed] and zero body force/traction.

    ``fixed`` is an (N, 3) mask of constrained components (vertex, axis); unconstrained
    boundary components are traction-free. Solves the P1 system K u = 0 condensed on the
    free components.
    """
    skfem, lame_parameters, linear_elasticity = _skfem()
    if not 0.0 <= poisson < 0.5 or young_kpa <= 0:
        raise TetdoseError(f"need E > 0 and 0 ≤ ν < 0.5, got E = {young_kpa} kPa, ν = {poisson}")
    m = skfem.MeshTet(np.ascontiguousarray(points_mm.T), np.ascontiguousarray(tets.T))
    basis = skfem.Basis(m, skfem.ElementVectorH1(skfem.ElementTetP1()))
    k = skfem.asm(linear_elasticity(*lame_parameters(young_kpa, poisson)), basis)
    dof = basis.nodal_dofs.T  # (N, 3): global dof of (vertex, component)
    x = np.zeros(basis.N)
    x[dof] = np.where(fixed, values_mm, 0.0)
    if fixed.all():
        return x[dof]
    return skfem.solve(*skfem.condense(k, x=x, D=dof[fixed]))[dof]


def propagate_boundary(mesh: TetMesh, vertex_ids: IntArray, displacement_mm: FloatArray, *,
                       n_increments: int = 1, young_kpa: float = YOUNG_KPA,
                       poisson: float = POISSON) -> FloatArray:
    """New vertex positions (N, 3) [mm] when ``vertex_ids`` move by ``displacement_mm``.

    The prescribed displacement is applied in ``n_increments`` equal steps, each solved on the
    geometry left by the previous one. An inverted tetrahedron at any step is a MeshError.
    """
    if n_increments < 1:
        raise TetdoseError(f"n_increments must be ≥ 1, got {n_increments}")
    ids = np.asarray(vertex_ids, dtype=np.intp)
    fixed = np.zeros((mesh.n_points, 3), dtype=bool)
    fixed[ids] = True
    step = np.zeros((mesh.n_points, 3))
    step[ids] = np.asarray(displacement_mm, dtype=np.float64) / n_increments
    pts = mesh.points_mm.copy()
    for i in range(n_increments):
        pts = pts + solve_linear_elastic(pts, mesh.tets, fixed, step, young_kpa=young_kpa,
                                         poisson=poisson)
        bad = np.flatnonzero(signed_volumes_mm3(pts, mesh.tets) <= 0)
        if len(bad):
            raise MeshError(
                f"{len(bad)} tetrahedra inverted at FEM increment {i + 1}/{n_increments}, ids "
                f"{bad[:20].tolist()}; use more increments or a finer/better-shaped mesh"
            )
    return pts


def boundary_surface(mesh: TetMesh) -> tuple[Surface, IntArray]:
    """The mesh's boundary as a Surface on its own vertex numbering, and the mesh vertex ids."""
    faces = mesh.boundary_faces
    ids, local = np.unique(faces, return_inverse=True)
    return Surface(mesh.points_mm[ids], local.reshape(faces.shape)), ids


def surface_driven_points(mesh: TetMesh, target: Surface, *, n_increments: int = 4,
                          young_kpa: float = YOUNG_KPA, poisson: float = POISSON) -> FloatArray:
    """Vertex positions (N, 3) [mm] of ``mesh`` deformed so its boundary lies on ``target``.

    1. rigid ICP of the boundary onto ``target``, applied to every vertex (strain free);
    2. each boundary vertex moves to its closest point on ``target``;
    3. the interior follows by incremental linear elasticity (:func:`propagate_boundary`).

    Closest-point matching puts every boundary vertex on the target but is not a
    correspondence: vertices on or near an edge of a stretched shape stay on the side faces, so
    for large non-rigid changes the deformed volume can fall short of the target's (a 15 %
    stretch of a box gives 7 %). Give phase meshes or a DVF when correspondence matters.
    """
    surf, ids = boundary_surface(mesh)
    rigid = icp(surf, target)
    moved = mesh.moved(rigid.apply(mesh.points_mm))
    cp, _ = closest_points(moved.points_mm[ids], target)
    return propagate_boundary(moved, ids, cp - moved.points_mm[ids], n_increments=n_increments,
                              young_kpa=young_kpa, poisson=poisson)
