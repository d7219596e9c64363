"""Mass conservation of the per-phase density update (paper eq. 10–13) on analytic motions.

For an affine motion x = F X + c every tetrahedron's volume changes by det F, so the exact
mass-conserving density is ρ_0 / det F everywhere: uniform scaling by s gives ρ_0 / s³, a rigid
motion leaves ρ_0 unchanged. Over a breathing cycle the total mass must stay the reference
mass (the L2 update is exactly conservative), and updating from the reference (never phase to
phase) brings the density back to ρ_0 when the mesh returns to the reference.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from tetdose.core.mesh import TetMesh
from tetdose.mapping.solve import lumped_mass_mm3
from tetdose.motion.breathing import BreathingModel
from tetdose.motion.conserve import mesh_mass_g, update_density, update_series


def kuhn_box(n: int, size_mm: float, seed: int) -> TetMesh:
    """A cube of n³ cells × 6 Kuhn tetrahedra with jittered interior vertices and a density."""
    ax = np.linspace(0.0, size_mm, n + 1)
    z, y, x = np.meshgrid(ax, ax, ax, indexing="ij")
    pts = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)
    interior = np.all((pts > 0) & (pts < size_mm), axis=1)
    rng = np.random.default_rng(seed)
    pts[interior] += rng.uniform(-0.15, 0.15, (interior.sum(), 3)) * size_mm / n

    def vid(c):
        return (c[2] * (n + 1) + c[1]) * (n + 1) + c[0]

    tets = []
    for cell in itertools.product(range(n), repeat=3):
        for perm in itertools.permutations(range(3)):
            c = np.array(cell)
            ids = [vid(c)]
            for a in perm:
                c = c.copy()
                c[a] += 1
                ids.append(vid(c))
            tets.append(ids)
    mesh = TetMesh(pts, np.array(tets)).with_fixed_orientation()
    mesh.check_cells()
    rho = 0.3 + rng.uniform(0.0, 1.5, mesh.n_points)  # rough field: lung to bone
    return mesh.with_data(point_data={"density": rho})


@pytest.fixture(scope="module")
def mesh() -> TetMesh:
    return kuhn_box(4, 40.0, seed=11)


def rotation(angles):
    out = np.eye(3)
    for axis, a in enumerate(angles):
        c, s = np.cos(a), np.sin(a)
        i, j = [k for k in range(3) if k != axis]
        r = np.eye(3)
        r[i, i], r[i, j], r[j, i], r[j, j] = c, -s, s, c
        out = r @ out
    return out


@pytest.mark.parametrize("method", ["l2", "lsq"])
@pytest.mark.parametrize(("s", "centre"), [(1.25, (0, 0, 0)), (0.8, (-300.0, 125.0, 40.0)),
                                           (1.07, (20.0, 20.0, 1000.0))])
def test_uniform_scaling_divides_density_by_s_cubed(mesh, method, s, centre):
    rho0 = mesh.point_data["density"]
    c = np.asarray(centre, dtype=float)
    phase = mesh.moved(c + s * (mesh.points_mm - c))
    rho = update_density(mesh, rho0, phase, method=method)
    np.testing.assert_allclose(rho, rho0 / s**3, rtol=1e-12)


@pytest.mark.parametrize("method", ["l2", "lsq"])
def test_rigid_motion_keeps_density(mesh, method):
    rho0 = mesh.point_data["density"]
    phase = mesh.moved(mesh.points_mm @ rotation([0.4, -1.1, 2.3]).T + [150.0, -80.0, 33.0])
    rho = update_density(mesh, rho0, phase, method=method)
    np.testing.assert_allclose(rho, rho0, rtol=1e-12)


def test_affine_motion_l2_gives_rho_over_det_f(mesh):
    """Any affine map: the pushed-forward density ρ_0/det F lies in P1, so L2 returns it."""
    rho0 = mesh.point_data["density"]
    f = np.array([[1.1, 0.2, 0.0], [-0.05, 0.95, 0.1], [0.0, 0.15, 1.2]])
    rho = update_density(mesh, rho0, mesh.moved(mesh.points_mm @ f.T), method="l2")
    np.testing.assert_allclose(rho, rho0 / np.linalg.det(f), rtol=1e-12)


def test_total_mass_constant_over_breathing_cycle(mesh):
    # The unlabelled mesh (region 0) taken as lung: the volume-changing motion.
    series = BreathingModel(amplitude_mm=12.0, n=2).series(mesh, 10, lung_regions=[0])
    out, reports = update_series(series)
    m0 = mesh_mass_g(mesh, mesh.point_data["density"])
    assert max(r.worst_volume_change for r in reports) > 0.2  # the motion is not trivial
    for k, r in enumerate(reports):
        phase = mesh.moved(series.points_mm[k])
        assert r.total_mass_g == pytest.approx(m0, rel=1e-9, abs=0)
        assert mesh_mass_g(phase, out.density_g_cm3[k]) == pytest.approx(m0, rel=1e-9, abs=0)
        assert r.min_density_g_cm3 >= 0.0
    # The same density is found at the same geometry: no drift from phase-to-phase updates.
    np.testing.assert_allclose(out.density_g_cm3[3], out.density_g_cm3[7], rtol=1e-12)
    np.testing.assert_allclose(out.density_g_cm3[5], mesh.point_data["density"], rtol=1e-12)


def test_l2_keeps_each_tet_mass_for_a_p1_pushforward(mesh):
    """For an affine motion the per-tetrahedron P1 mass V_k·mean(ρ at its vertices) is kept."""
    rho0 = mesh.point_data["density"]
    f = np.diag([1.3, 0.9, 1.1])
    phase = mesh.moved(mesh.points_mm @ f.T)
    rho = update_density(mesh, rho0, phase)
    m_ref = mesh.volumes_mm3 * rho0[mesh.tets].mean(axis=1)
    m_phase = phase.volumes_mm3 * rho[phase.tets].mean(axis=1)
    np.testing.assert_allclose(m_phase, m_ref, rtol=1e-12)
    assert lumped_mass_mm3(phase).sum() == pytest.approx(np.prod(np.diag(f)) * 40.0**3)
