"""Kernels of dose mode against independent references: the mass-thickness segment walker vs
brute-force chords, the photo-electron (Sauter) and pair angular samplers vs their analytic
CDFs, Compton recoil kinematics, the volume source's density-weighted points, the hard-event
majorant, and settings/plan validation."""

from __future__ import annotations

import argparse
import math

import numpy as np
import pytest
from numba import njit

from tetdose._random import next_uniform, seed_for
from tetdose.cli._dose import add_run_args, run_settings
from tetdose.core.mesh import TetMesh
from tetdose.errors import PlanError
from tetdose.plan.model import Plan
from tetdose.plan.volume_source import VolumeSource
from tetdose.transport.geometry._voxel import VoxelGeometry
from tetdose.transport.geometry._world import WorldGeometry
from tetdose.transport.geometry.tets import mesh_geometry
from tetdose.transport.history._segment import (
    SEG_DONE,
    SEG_ESCAPED,
    SEG_MATERIAL,
    segment,
)
from tetdose.transport.physics._photon import (
    grid_position,
    majorant_at,
    sample_klein_nishina,
    transport_coefficients,
)
from tetdose.transport.physics._photon_electrons import (
    ELECTRON_MASS_MEV,
    compton_electron_direction,
    sample_leading_term_cos,
    sample_sauter_cos,
)
from tetdose.transport.physics.electron_xs import build_electron_tables
from tetdose.transport.physics.xs import build_cross_sections
from tetdose.transport.run.coupled import hard_majorant, photon_majorant
from tetdose.transport.run.settings import TransportSettings
from tetdose.transport.sources._volume import VolumeArrays, sample_volume

import helpers
from helpers import ray_interval

MC2 = ELECTRON_MASS_MEV


def _mesh_world(mesh, rho, material):
    g = mesh_geometry(mesh, rho, np.asarray(material, dtype=np.intp))
    vox = VoxelGeometry(np.zeros(3), np.ones(3), np.zeros(3, np.intp), np.zeros(0),
                        np.zeros(0, np.intp))
    z3 = np.zeros(3, np.intp)
    return WorldGeometry(g, vox, z3, z3.copy(), np.zeros(1, np.intp), np.zeros(0, np.intp))


def _chords(mesh, rho, p, d):
    """{tet: (t_in, t_out, ρ(t_in), ρ(t_out))} of the ray p + t·d, t ≥ 0 (half-space clipping)."""
    out = {}
    for k, tet in enumerate(mesh.tets):
        v = mesh.points_mm[tet]
        t_in, t_out = ray_interval(v, p, d)
        if t_out - t_in > 1e-9:
            m = np.linalg.solve(np.vstack([v.T, np.ones(4)]), np.eye(4))
            rho_at = lambda t: float(m @ np.append(p + t * d, 1.0) @ rho[tet])  # noqa: E731,B023
            out[k] = (t_in, t_out, rho_at(t_in), rho_at(t_out))
    return out


def _column_to(chords, t_end):
    """Column density [mm·g/cm³] along the chords from t = 0 to t_end (ρ linear on each)."""
    col = 0.0
    for t0, t1, r0, r1 in chords.values():
        b = min(t1, t_end)
        if b > t0:
            r_b = r0 + (r1 - r0) * (b - t0) / (t1 - t0)
            col += 0.5 * (r0 + r_b) * (b - t0)
    return col


@pytest.fixture(scope="module")
def jittered():
    mesh = helpers.box_mesh((0, 0, 0), (30, 30, 30), (3, 3, 3), jitter=0.25, seed=4)
    rho = np.random.default_rng(2).uniform(0.3, 1.8, mesh.n_points)
    return mesh, rho


def test_segment_columns_per_tet_match_brute_force(jittered):
    mesh, rho = jittered
    wg = _mesh_world(mesh, rho, np.zeros(mesh.n_tets))
    rng = np.random.default_rng(3)
    bcell, bcol = np.empty(256, np.intp), np.empty(256)
    counts = np.zeros(9, np.int64)
    for _ in range(30):
        k = int(rng.integers(mesh.n_tets))
        p = mesh.points_mm[mesh.tets[k]].T @ rng.dirichlet(np.ones(4))
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        out, *_, left, nb = segment(wg, k, -1, *p, *d, 1e4, 0, bcell, bcol, 0, counts)
        chords = _chords(mesh, rho, p, d)
        ref = {kk: _column_to({kk: c}, np.inf) for kk, c in chords.items()}
        got = dict(zip(bcell[:nb].tolist(), bcol[:nb].tolist(), strict=True))
        assert out == SEG_ESCAPED
        # the kernel's face planes are float32: within 2⁻²⁴·|c| (< 3·10⁻⁶ mm here) of the vertices
        assert {kk for kk, c in ref.items() if c > 1e-5} <= set(got)
        for kk, c in got.items():
            assert c == pytest.approx(ref.get(kk, 0.0), rel=1e-9, abs=1e-5)
        assert 1e4 - left == pytest.approx(sum(ref.values()), rel=1e-9, abs=1e-5)


def test_segment_ends_where_the_column_is_used_up(jittered):
    """The end point of a segment of column C lies where ∫ρ dl along the ray reaches C (exact
    root of the linear density, no sub-stepping)."""
    mesh, rho = jittered
    wg = _mesh_world(mesh, rho, np.zeros(mesh.n_tets))
    rng = np.random.default_rng(5)
    bcell, bcol = np.empty(256, np.intp), np.empty(256)
    counts = np.zeros(9, np.int64)
    for _ in range(30):
        k = int(rng.integers(mesh.n_tets))
        p = mesh.points_mm[mesh.tets[k]].T @ rng.dirichlet(np.ones(4))
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        chords = _chords(mesh, rho, p, d)
        need = rng.uniform(0.1, 0.9) * _column_to(chords, np.inf)
        out, cell, _e, x, y, z, left, nb = segment(wg, k, -1, *p, *d, need, 0, bcell, bcol, 0,
                                                   counts)
        t_end = float(np.dot(np.array([x, y, z]) - p, d))
        assert out == SEG_DONE and left == 0.0
        assert _column_to(chords, t_end) == pytest.approx(need, rel=1e-9)
        assert bcol[:nb].sum() == pytest.approx(need, rel=1e-12)
        assert chords[cell][0] - 1e-9 <= t_end <= chords[cell][1] + 1e-9


def test_segment_stops_at_a_material_change():
    mesh = helpers.box_mesh((0, 0, 0), (30, 30, 30), (3, 3, 3))
    material = (mesh.centroids_mm[:, 0] > 20.0).astype(np.intp)
    wg = _mesh_world(mesh, np.ones(mesh.n_points), material)
    bcell, bcol = np.empty(256, np.intp), np.empty(256)
    k = int(np.argmin(np.linalg.norm(mesh.centroids_mm - [5.0, 12.0, 13.0], axis=1)))
    p = mesh.centroids_mm[k]
    out, cell, entry, x, y, z, left, nb = segment(wg, k, -1, *p, 1.0, 0.0, 0.0, 1e3, 0, bcell,
                                                  bcol, 0, np.zeros(9, np.int64))
    assert out == SEG_MATERIAL and material[cell] == 1 and entry >= 0
    assert x == pytest.approx(20.0, abs=1e-9)
    assert 1e3 - left == pytest.approx(20.0 - p[0], rel=1e-12)  # ρ = 1 g/cm³


def test_segment_crosses_vacuum_gaps_without_using_column():
    """Two cubes 10 mm apart in vacuum: a segment passes from one to the other (no column in
    the gap) and escapes beyond."""
    a = helpers.box_mesh((0, 0, 0), (10, 10, 10), (2, 2, 2))
    b = helpers.box_mesh((20, 0, 0), (30, 10, 10), (2, 2, 2))
    mesh = TetMesh(np.vstack([a.points_mm, b.points_mm]),
                   np.vstack([a.tets, b.tets + a.n_points]))
    rho = np.where(mesh.points_mm[:, 0] < 15, 1.0, 2.0)
    wg = _mesh_world(mesh, rho, np.zeros(mesh.n_tets))
    bcell, bcol = np.empty(256, np.intp), np.empty(256)
    k = int(np.argmin(np.linalg.norm(mesh.centroids_mm - [1.0, 3.3, 6.2], axis=1)))
    p = mesh.centroids_mm[k]
    d = np.array([1.0, 0.01, 0.0]) / np.hypot(1.0, 0.01)
    out, *_, left, nb = segment(wg, k, -1, *p, *d, 1e3, 0, bcell, bcol, 0,
                                np.zeros(9, np.int64))
    assert out == SEG_ESCAPED
    expected = (10.0 - p[0]) / d[0] * 1.0 + 10.0 / d[0] * 2.0
    assert 1e3 - left == pytest.approx(expected, rel=1e-12)
    step = 1e3 - left - 5.0  # stop inside the second cube: 5 mm·g/cm³ before its end
    out, cell, *_ = segment(wg, k, -1, *p, *d, step, 0, bcell, bcol, 0, np.zeros(9, np.int64))
    assert out == SEG_DONE and mesh.centroids_mm[cell, 0] > 20.0


@njit(cache=True)
def _draw(kind, t_mev, n, seed):
    out = np.empty(n)
    state = seed_for(seed, 0, 0)
    for i in range(n):
        if kind == 0:
            state, out[i] = sample_sauter_cos(t_mev, state)
        else:
            state, out[i] = sample_leading_term_cos(t_mev, state)
    return out


def _beta_gamma(t):
    gamma = 1.0 + t / MC2
    return math.sqrt(1.0 - 1.0 / gamma**2), gamma


def _sauter_pdf(mu, t):
    beta, gamma = _beta_gamma(t)
    x = 1.0 - beta * mu
    return (1.0 - mu * mu) / x**4 * (1.0 + 0.5 * gamma * (gamma - 1.0) * (gamma - 2.0) * x)


def _chi2_against(samples, pdf):
    """χ² of a 40-bin histogram of cos θ against the numerically integrated pdf."""
    edges = np.linspace(-1.0, 1.0, 41)
    fine = np.linspace(-1.0, 1.0, 400_001)
    dens = pdf(fine)
    cdf = np.concatenate([[0.0], np.cumsum(0.5 * (dens[1:] + dens[:-1]) * np.diff(fine))])
    p = np.diff(np.interp(edges, fine, cdf / cdf[-1]))
    counts, _ = np.histogram(samples, edges)
    keep = p * len(samples) > 20
    expected = p[keep] * len(samples)
    return float(np.sum((counts[keep] - expected) ** 2 / expected)), int(keep.sum())


@pytest.mark.parametrize("t_mev", [0.02, 0.3, 3.0])
def test_sauter_sampler_follows_the_sauter_distribution(t_mev):
    s = _draw(0, t_mev, 200_000, 11)
    chi2, dof = _chi2_against(s, lambda mu: _sauter_pdf(mu, t_mev))
    assert chi2 < dof + 5 * math.sqrt(2 * dof), chi2


@pytest.mark.parametrize("t_mev", [0.05, 1.0, 10.0])
def test_pair_angle_sampler_follows_the_leading_term(t_mev):
    beta, _ = _beta_gamma(t_mev)
    s = _draw(1, t_mev, 200_000, 12)
    chi2, dof = _chi2_against(s, lambda mu: 1.0 / (1.0 - beta * mu) ** 2)
    assert chi2 < dof + 5 * math.sqrt(2 * dof), chi2


@njit(cache=True)
def _compton(e, n):
    out = np.empty((n, 7))
    state = seed_for(3, 0, 0)
    for i in range(n):
        state, e_out, cos_t = sample_klein_nishina(e, state)
        sin_t = math.sqrt(max(0.0, 1.0 - cos_t * cos_t))
        state, r = next_uniform(state)
        phi = 2.0 * math.pi * r
        u2, v2, w2 = sin_t * math.cos(phi), sin_t * math.sin(phi), cos_t
        eu, ev, ew = compton_electron_direction(e, e_out, 0.0, 0.0, 1.0, u2, v2, w2)
        out[i] = e_out, u2, v2, w2, eu, ev, ew
    return out


def test_compton_electron_carries_the_momentum_the_photon_lost():
    """E·ẑ = E'·d' + p_e with |p_e|c = sqrt(T(T + 2mc²)), T = E − E': the recoil direction and
    the Klein–Nishina energy and angle agree with relativistic two-body kinematics."""
    e = 2.0
    r = _compton(e, 2000)
    e_out, d_photon, d_electron = r[:, 0], r[:, 1:4], r[:, 4:]
    t = e - e_out
    p_e = np.sqrt(t * (t + 2 * MC2))[:, None] * d_electron
    balance = e_out[:, None] * d_photon + p_e
    np.testing.assert_allclose(balance, np.tile([0.0, 0.0, e], (len(r), 1)), atol=1e-9)
    assert np.all(d_electron[:, 2] >= -1e-12)  # the recoil electron never goes backwards


@njit(cache=True)
def _volume_points(wg, vol, n):
    out = np.empty((n, 4))
    state = seed_for(7, 1, 0)
    for i in range(n):
        state, sp, e, cell, x, y, z, u, v, w = sample_volume(wg, vol, state)
        out[i, 0], out[i, 1], out[i, 2], out[i, 3] = float(cell), x, y, z
    return out


def test_volume_points_follow_the_linear_density_in_a_tet():
    """ρ-weighted points in a tet (ρ = Σρᵢλᵢ): by the Dirichlet(1,1,1,1) moments of uniform
    barycentric coordinates, E[λᵢ] = (Σρ + ρᵢ)/(5Σρ), so x̄ = Σᵢ pᵢ (Σρ + ρᵢ)/(5Σρ), and
    E[λ₀²] = (Σρ + 2ρ₀)/(15Σρ)."""
    pts = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.0, 7.0, 0.0], [1.0, 2.0, 9.0]])
    rho = np.array([0.2, 3.0, 1.0, 0.5])
    mesh = TetMesh(pts, np.array([[0, 1, 2, 3]])).with_fixed_orientation()
    wg = _mesh_world(mesh, rho, [0])
    vol = VolumeArrays(np.ones(1), np.zeros(1, np.intp), np.array([0, 1]), np.ones(1),
                       np.ones(1), np.array([0, 1]), np.zeros(1, np.intp), np.ones(1),
                       np.ascontiguousarray(mesh.tets, dtype=np.intp), pts.copy(), rho.copy())
    n = 400_000
    got = _volume_points(wg, vol, n)[:, 1:]
    s = rho.sum()
    mean = ((s + rho)[:, None] * pts).sum(axis=0) / (5 * s)
    lam = np.linalg.solve(np.vstack([pts.T, np.ones(4)]), np.vstack([got.T, np.ones(n)]))
    assert lam.min() > -1e-9  # inside the tet
    spread = got.std(axis=0) / math.sqrt(n)
    assert np.all(np.abs(got.mean(axis=0) - mean) < 5 * spread)
    e_l0 = (s + 2 * rho[0]) / (15 * s)
    assert abs(np.mean(lam[0] ** 2) - e_l0) < 5 * np.std(lam[0] ** 2) / math.sqrt(n)


def test_volume_source_cells_are_drawn_by_mass():
    from tetdose.transport.geometry.world import World, world_arrays
    from tetdose.transport.run.job import assign_materials
    from tetdose.transport.sources.volume import volume_arrays

    mesh = helpers.box_mesh((0, 0, 0), (20, 20, 20), (2, 2, 2))
    region = np.where(mesh.centroids_mm[:, 2] < 10, 1, 2)
    rho = 0.5 + 0.1 * mesh.points_mm[:, 0]
    mesh = TetMesh(mesh.points_mm, mesh.tets, region, {"density": rho})
    world = World(mesh=mesh)
    plan = Plan(materials={1: "water", 2: "water"},
                volume_sources=(VolumeSource("electron", (1.0,), region=2),))
    arrays = world_arrays(world, lambda r, reg: assign_materials(r, reg, plan))
    vol = volume_arrays(plan.volume_sources, world, arrays)
    n = 200_000
    cells = _volume_points(arrays.geometry, vol, n)[:, 0].astype(int)
    mesh_cells = arrays.order[cells]  # kernel tet → mesh tet
    assert np.all(mesh.region[mesh_cells] == 2)
    freq = np.bincount(mesh_cells, minlength=mesh.n_tets)[region == 2] / n
    mass = arrays.mass_g[region == 2] / arrays.mass_g[region == 2].sum()
    assert np.all(np.abs(freq - mass) < 5 * np.sqrt(mass * (1 - mass) / n))
    with pytest.raises(PlanError, match="region 7"):
        volume_arrays((VolumeSource("electron", (1.0,), region=7),), world, arrays)


def test_majorant_bounds_the_hard_cross_section_over_a_step():
    et = build_electron_tables(["water", "cortical_bone"], cutoff_mev=0.05, photon_cutoff_mev=0.01)
    f = 0.25
    sig_hat = hard_majorant(et, f)
    from tetdose.transport.physics._electron import electron_position, hard_cross_sections

    rng = np.random.default_rng(1)
    for e in np.exp(rng.uniform(np.log(0.06), np.log(19.0), 300)):
        i, _ = electron_position(et, e)
        for m in (0, 1):
            for sp in (0, 1):
                for e2 in np.linspace(e * (1 - f), e, 7):
                    if e2 > et.cutoff_mev:
                        assert sum(hard_cross_sections(et, m, sp, e2)) <= sig_hat[m, sp, i]


@pytest.mark.parametrize("kwargs, match", [
    ({"physics": "quantum"}, "physics"),
    ({"physics": "dose", "estimator": "track_length"}, "track-length"),
    ({"electron_cutoff_mev": 0.0}, "electron_cutoff_mev"),
    ({"max_energy_loss_fraction": 0.9}, "max_energy_loss_fraction"),
    ({"photon_tracking": "delta"}, "photon_tracking"),
])
def test_bad_electron_settings_raise_plan_error(kwargs, match):
    with pytest.raises(PlanError, match=match):
        TransportSettings(100, 10, **kwargs)


def test_default_settings_are_dose_with_analog_scoring_and_kerma_keeps_track_length():
    assert TransportSettings(100).physics == "dose"
    assert TransportSettings(100).estimator == "analog"
    assert TransportSettings(100, physics="kerma").estimator == "track_length"
    assert TransportSettings(100).photon_tracking == "woodcock"


def test_cli_photon_tracking_reaches_the_settings():
    parser = argparse.ArgumentParser()
    add_run_args(parser)
    for argv, tracking in (([], "woodcock"), (["--photon-tracking", "walk"], "walk")):
        args = parser.parse_args(["--histories", "100", *argv])
        assert run_settings(args).photon_tracking == tracking


def test_cli_splitting_scheme_reaches_the_settings():
    parser = argparse.ArgumentParser()
    add_run_args(parser)
    for argv, scheme in (([], "roulette"), (["--splitting-scheme", "follow"], "follow"),
                         (["--splitting-scheme", "repeat", "--photon-splitting", "8"], "repeat")):
        args = parser.parse_args(["--histories", "100", *argv])
        assert run_settings(args).splitting_scheme == scheme
    with pytest.raises(SystemExit):
        parser.parse_args(["--histories", "100", "--splitting-scheme", "xvmc"])


def test_cli_max_energy_loss_fraction_reaches_the_settings():
    parser = argparse.ArgumentParser()
    add_run_args(parser)
    for argv, f_loss in (([], 0.25), (["--max-energy-loss-fraction", "0.5"], 0.5)):
        args = parser.parse_args(["--histories", "100", *argv])
        assert run_settings(args).max_energy_loss_fraction == f_loss
    for bad in ("0.6", "0", "nan"):
        with pytest.raises(SystemExit):
            parser.parse_args(["--histories", "100", "--max-energy-loss-fraction", bad])


def test_cli_secondary_photon_splitting_reaches_the_settings():
    parser = argparse.ArgumentParser()
    add_run_args(parser)
    args = parser.parse_args(["--histories", "100", "--photon-splitting", "64",
                              "--splitting-scheme", "repeat", "--secondary-photon-splitting", "32"])
    st = run_settings(args)
    assert (st.photon_splitting, st.secondary_photon_splitting, st.secondary_copies) == (64, 32, 32)
    assert run_settings(parser.parse_args(["--histories", "100"])).secondary_photon_splitting is None
    with pytest.raises(SystemExit):
        parser.parse_args(["--histories", "100", "--secondary-photon-splitting", "0"])


def test_photon_majorant_bounds_every_material_between_the_nodes():
    """μ̂(E) ≥ (μ/ρ)_m(E)·ρ_max,m for every material at energies between the table's nodes (as
    the kernels interpolate), within 2 % of the largest of them; a material of density 0 (none
    in the box) is left out."""
    xs = build_cross_sections(["water", "lung", "cortical_bone", "adipose"])
    rho = np.array([1.1, 0.4, 1.9, 0.0])
    hat = photon_majorant(xs, rho)
    np.testing.assert_array_equal(hat, photon_majorant(xs, np.array([1.1, 0.4, 1.9])))
    for e in np.geomspace(0.0105, 19.9, 1999):
        i, f = grid_position(xs, e)
        mu_hat = majorant_at(hat, i, f)
        mu = max(transport_coefficients(xs, m, e)[0] * rho[m] for m in range(3))
        assert mu <= mu_hat <= 1.02 * mu, e


def test_plan_toml_particles_and_volume_sources(tmp_path):
    (tmp_path / "plan.toml").write_text(
        '[[beam]]\ntype = "pencil"\nparticle = "electron"\nenergy_mev = 6.0\n'
        'position_mm = [0.0, 0.0, -10.0]\n'
        '[[beam]]\ntype = "volume"\nparticle = "positron"\nenergy_mev = 0.6\nregion = 3\n'
        'weight = 2.0\n')
    plan = Plan.from_toml(tmp_path / "plan.toml")
    assert [b.particle for b in plan.beams] == ["electron"]
    (vol,) = plan.volume_sources
    assert (vol.particle, vol.region, vol.weight) == ("positron", 3, 2.0)
    assert list(vol.energies_mev) == [0.6]
    with pytest.raises(PlanError, match="particle"):
        Plan.from_dict({"beam": [{"type": "volume", "particle": "neutron", "energy_mev": 1.0}]})
    with pytest.raises(PlanError, match="region"):
        Plan.from_dict({"beam": [{"type": "volume", "energy_mev": 1.0, "region": "liver"}]})


def test_volume_points_in_a_hybrid_world_follow_the_mass_outside_the_mesh():
    """A mesh cube cutting voxels (faces off the voxel planes) inside a CT: cells are drawn by
    mass (the voxels' mass is their part outside the mesh), and no point drawn in a voxel lies
    inside the mesh."""
    from tetdose.core.image import Image
    from tetdose.transport.geometry._world import start_cell
    from tetdose.transport.geometry.world import World, world_arrays
    from tetdose.transport.run.job import assign_materials
    from tetdose.transport.sources.volume import volume_arrays

    grid = helpers.grid_for((0, 0, 0), (20, 20, 20), (5.0, 5.0, 5.0))
    mesh = helpers.box_mesh((3.5, 3.5, 3.5), (13.5, 13.5, 13.5), (2, 2, 2))
    mesh = mesh.with_data(point_data={"density": np.full(mesh.n_points, 1.5)})
    world = World(mesh=mesh, density=Image(np.ones(grid.shape), grid))
    plan = Plan(volume_sources=(VolumeSource("electron", (1.0,)),))
    arrays = world_arrays(world, lambda r, reg: assign_materials(r, reg, plan))
    frame = lambda p: grid.to_grid_frame(p)  # noqa: E731
    vol = volume_arrays(plan.volume_sources, world, arrays, frame)
    n = 200_000
    got = _volume_points(arrays.geometry, vol, n)
    cells = got[:, 0].astype(int)
    m_tets = mesh.n_tets
    mass = arrays.mass_g.copy()
    mass[:m_tets] = arrays.mass_g[:m_tets][arrays.order]  # kernel order
    p = mass / mass.sum()
    freq = np.bincount(cells, minlength=len(mass)) / n
    assert np.all(np.abs(freq - p) < 5 * np.sqrt(p * (1 - p) / n) + 1e-12)
    in_voxels = got[cells >= m_tets][:3000]
    for _c, x, y, z in in_voxels:
        cell, *_ = start_cell(arrays.geometry, x, y, z, 0.0, 0.0, 1.0)
        assert cell >= m_tets


def test_source_mix_is_the_group_cdf_the_kernel_draws_from():
    """Issue 27: how a volume source shares histories with beams is recorded (``source_mix``)
    and is the kernel's group cdf: weight / Σ weight, a beam's weight in its units (MU)."""
    from tetdose.core.image import Image
    from tetdose.plan.photon_source import PhotonSource
    from tetdose.transport.geometry.world import World, world_arrays
    from tetdose.transport.run.job import assign_materials
    from tetdose.transport.sources.species import GROUPS, particle_sources, source_mix
    from tetdose.transport.sources.volume import volume_arrays

    grid = helpers.grid_for((0, 0, 0), (20, 20, 20), (5.0, 5.0, 5.0))
    world = World(density=Image(np.ones(grid.shape), grid))
    beam = PhotonSource("pencil", (10.0, 10.0, -5.0), (0.0, 0.0, 1.0), energies_mev=(1.0,),
                        weight=3.0)
    plan = Plan((beam,), volume_sources=(VolumeSource("electron", (1.0,), weight=1.0),))
    assert source_mix(Plan((beam,))) is None  # photon beams alone: nothing to say
    mix = source_mix(plan)
    assert mix["fraction_of_histories"] == {"photon": 0.75, "electron": 0.0, "positron": 0.0,
                                            "volume": 0.25}
    arrays = world_arrays(world, lambda r, reg: assign_materials(r, reg, plan))
    vol = volume_arrays(plan.volume_sources, world, arrays, lambda p: grid.to_grid_frame(p))
    _, groups = particle_sources(plan, TransportSettings(100, physics="dose"),
                                 lambda a, d: a @ grid.direction if d else grid.to_grid_frame(a),
                                 vol)
    fractions = np.diff(np.r_[0.0, groups.group_cdf])
    np.testing.assert_allclose(fractions, [mix["fraction_of_histories"][g] for g in GROUPS])
