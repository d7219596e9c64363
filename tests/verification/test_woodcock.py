"""Woodcock (delta) tracking of photons through the mesh (dose mode) against the exact answer and
the tet walk: uncollided transmission exp(−∫μ ds) through linear-density tets (mesh in vacuum,
and a notched mesh inside voxels), and the dose per region with Woodcock and with the walk on a
water / lung / bone tet slab and on the hybrid world."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numba import njit
from test_dose_transport import _closes
from test_dose_variance_reduction import LAYERS, SLAB_PLAN
from test_hybrid import _batch_sums, _z

from tetdose._constants import MM_PER_CM
from tetdose._random import next_uniform, seed_for
from tetdose.core.mesh import TetMesh
from tetdose.transport import PhotonSource, Plan, TransportSettings, World, simulate
from tetdose.transport.geometry._world import WorldGeometry, start_cell
from tetdose.transport.history._delta import flight_delta
from tetdose.transport.history._electron import N_COUNTS_DOSE
from tetdose.transport.history._photon import ESCAPES, flight
from tetdose.transport.physics._photon import transport_coefficients
from tetdose.transport.run.coupled import majorant_densities, photon_majorant
from tetdose.transport.run.job import build_job, cross_sections

import helpers

MATERIALS = {1: "water", 2: "lung", 3: "cortical_bone"}


def _slab_mesh(notch: bool = False) -> TetMesh:
    """60 × 60 × 80 mm tets along z in LAYERS (water 0–20, lung 20–40, bone 40–50, water 50–80),
    5 mm cubes, densities jumping between layers (vertices split per region) and linear inside
    the first water layer (1 + 0.005·x) and the lung (0.2 + 0.006·(z − 20)). ``notch``: the tets
    of x > 0, y > 0, 20 < z < 50 removed (a non-convex mesh; voxels fill the notch)."""
    mesh = helpers.box_mesh((-30, -30, 0), (30, 30, 80), (12, 12, 16))
    c = mesh.centroids_mm
    keep = np.ones(mesh.n_tets, bool)
    if notch:
        keep = ~((c[:, 0] > 0) & (c[:, 1] > 0) & (c[:, 2] > 20) & (c[:, 2] < 50))
    region = np.select([c[:, 2] < hi for _, hi, _, _ in LAYERS], [lab for *_, lab in LAYERS])
    region[c[:, 2] > 50] = 4  # the second water layer: its own vertex densities
    mesh = TetMesh(mesh.points_mm, mesh.tets[keep], region[keep]).split_by_region()
    p = mesh.points_mm
    reg = np.zeros(mesh.n_points, int)
    reg[mesh.tets.ravel()] = np.repeat(mesh.region, 4)
    rho = np.select([reg == 1, reg == 2, reg == 3], [1.0 + 0.005 * p[:, 0],
                                                      0.2 + 0.006 * (p[:, 2] - 20.0), 1.85], 1.0)
    region = np.where(mesh.region == 4, 1, mesh.region)
    return TetMesh(p, mesh.tets, region, {**mesh.point_data, "density": rho})


def _density_along(p: np.ndarray, d: np.ndarray, z0: float, z1: float) -> float:
    """∫ρ ds [mm·g/cm³] of _slab_mesh's field between planes z0 < z1 along the ray (ρ linear on
    the stretch: its value at the middle times the length)."""
    t0, t1 = (z0 - p[2]) / d[2], (z1 - p[2]) / d[2]
    m = p + 0.5 * (t0 + t1) * d
    rho = {(0, 20): 1.0 + 0.005 * m[0], (20, 40): 0.2 + 0.006 * (m[2] - 20.0)}
    return rho.get((z0, z1), 1.85 if z0 == 40 else 1.0) * (t1 - t0)


@njit(cache=True)
def _escaped_uncollided(wg, xs, ln_mu_hat, e, p, d, n, seed):
    """Fraction of ``n`` photons from p along d that reach no interaction (one flight each):
    Woodcock flights with a majorant table, walks when it is empty."""
    tally = np.zeros(1)
    counts = np.zeros(N_COUNTS_DOSE, dtype=np.int64)
    escaped = 0
    for h in range(n):
        state, xi = next_uniform(seed_for(seed, 0, h))
        cell, x, y, z, _ = start_cell(wg, p[0], p[1], p[2], d[0], d[1], d[2])
        tau = -math.log(1.0 - xi)
        if ln_mu_hat.shape[0] > 0:
            state, out, _, _, _, _ = flight_delta(wg, xs, ln_mu_hat, e, cell, x, y, z, d[0],
                                                  d[1], d[2], tau, state, tally, counts)
        else:
            out, _, _, _, _ = flight(wg, xs, e, cell, x, y, z, d[0], d[1], d[2], tau, False,
                                     tally, counts)
        escaped += out == ESCAPES
    return escaped / n, counts


def _transmission(world: World, e: float, p, d, n: int = 200_000) -> dict[str, tuple]:
    """{"woodcock" | "walk": (uncollided fraction, counts)} and the job (names, geometry)."""
    plan = Plan((PhotonSource("pencil", p, d, energies_mev=[e]),), materials=MATERIALS)
    settings = TransportSettings(10, 2)
    job, _ = build_job(world, plan, settings)
    xs = cross_sections(job, settings)
    wg = WorldGeometry(*job.geom)
    hat = photon_majorant(xs, majorant_densities(job.geom, len(job.names)))
    p, d = np.asarray(p, float), np.asarray(d, float) / np.linalg.norm(d)
    if world.grid is not None:  # the kernels work in the grid's frame
        p, d = world.grid.to_grid_frame(p[None])[0], d @ world.grid.direction
    out = {name: _escaped_uncollided(wg, xs, table, e, p, d, n, 5)
           for name, table in (("woodcock", hat), ("walk", np.zeros(0)))}
    return out, job, xs


def _check(out: dict, tau: float, n: int = 200_000) -> None:
    expected = math.exp(-tau)
    sigma = math.sqrt(expected * (1.0 - expected) / n)
    for name, (frac, _) in out.items():
        assert abs(frac - expected) < 3.0 * sigma, (name, frac, expected, sigma)


@pytest.mark.parametrize("e_mev", [0.1, 3.0])
def test_uncollided_transmission_through_linear_density_tets_is_exact(e_mev):
    """A pencil beam slanted through the tet slab (vacuum around): the fraction of photons whose
    first flight escapes is exp(−Σ_m (μ/ρ)_m ∫ρ ds) within 3σ (σ ≈ 0.1 %), with Woodcock
    tracking (bone sets the majorant; in lung most collisions are fictitious) as with the walk."""
    p, d = np.array([-3.0, 2.0, -10.0]), np.array([0.2, 0.1, 1.0])
    out, job, xs = _transmission(World(mesh=_slab_mesh()), e_mev, p, d)
    u = d / np.linalg.norm(d)
    mu = {name: transport_coefficients(xs, job.names.index(name), e_mev)[0]
          for name in MATERIALS.values()}
    tau = sum(mu[MATERIALS[lab]] * _density_along(p, u, lo, hi) for lo, hi, _, lab in LAYERS)
    _check(out, tau / MM_PER_CM)
    assert out["woodcock"][1][9] > 0 and out["walk"][1][9] == 0  # Woodcock steps, walk none
    assert out["woodcock"][1][3] == 0  # and no tet crossed


def test_uncollided_transmission_through_a_notched_mesh_inside_voxels_is_exact():
    """Hybrid world: the notched tet slab (z 0–80) inside a 5 mm CT of water (1.0; bone 1.85
    from z = 70, under the mesh but for 80–90). A pencil along z through the notch crosses CT
    water, mesh water, CT water in the notch (inside the mesh's box: Woodcock sees the voxels
    there), mesh water, CT bone: transmission exp(−∫μ ds) within 3σ."""
    grid = helpers.grid_for((-40, -40, -10), (40, 40, 90), (5.0, 5.0, 5.0))
    ct = helpers.density_image(grid, lambda x, y, z: np.where(z < 70, 1.0, 1.85))
    p, d = np.array([7.3, 11.1, -20.0]), np.array([0.0, 0.0, 1.0])
    out, job, xs = _transmission(World(mesh=_slab_mesh(notch=True), density=ct), 0.3, p, d)
    vox_mat = job.geom.vox.material
    water_ct, bone_ct = (int(m if m >= 0 else -m - 1) for m in (vox_mat[0], vox_mat[-1]))
    mu = {name: transport_coefficients(xs, job.names.index(name), 0.3)[0]
          for name in MATERIALS.values()}
    mu_ct = [transport_coefficients(xs, m, 0.3)[0] for m in (water_ct, bone_ct)]
    # CT water z −10–0 and 20–50 (the notch), CT bone 80–90; mesh water 0–20 (linear in x)
    # and 50–80
    tau = (mu_ct[0] * 1.0 * (10.0 + 30.0) + mu_ct[1] * 1.85 * 10.0
           + mu["water"] * (_density_along(p, d, 0, 20) + 30.0))
    _check(out, tau / MM_PER_CM)


def _slab_ct():
    """A 5 mm CT of the slab layers: water to z 20, lung 0.26 to 50, water to 70, bone 1.85."""
    grid = helpers.grid_for((-40, -40, -10), (40, 40, 90), (5.0, 5.0, 5.0))
    return grid, helpers.density_image(grid, lambda x, y, z: np.select(
        [z < 20, z < 50, z < 70], [1.0, 0.26, 1.0], 1.85))


@pytest.mark.parametrize("e_mev", [0.1, 3.0])
def test_uncollided_transmission_through_a_voxel_only_world_is_exact(e_mev):
    """Voxel-only world (no mesh): Woodcock flights in the grid's box (bone sets the majorant,
    lung and water collisions are partly fictitious) and the voxel walk both give
    exp(−Σ μ ρ L) within 3σ for a slanted pencil; Woodcock makes no voxel step."""
    _, ct = _slab_ct()
    p, d = np.array([-3.0, 2.0, -20.0]), np.array([0.1, 0.05, 1.0])
    out, job, xs = _transmission(World(density=ct), e_mev, p, d)
    vox = job.geom.vox
    mu_w, mu_l, mu_b = (transport_coefficients(xs, int(vox.material[np.isclose(vox.density,
                                                                              rho)][0]), e_mev)[0]
                        for rho in (1.0, 0.26, 1.85))
    sec = np.linalg.norm(d) / d[2]  # path length per mm of depth
    tau = sec * (mu_w * 1.0 * (30.0 + 20.0) + mu_l * 0.26 * 30.0 + mu_b * 1.85 * 20.0)
    _check(out, tau / MM_PER_CM)
    assert out["woodcock"][1][9] > 0 and out["woodcock"][1][4] == 0  # no voxel walked
    assert out["walk"][1][9] == 0 and out["walk"][1][4] > 0


def _region_energy(r, cells: dict[str, np.ndarray]) -> dict[str, tuple[float, float]]:  # noqa: ANN001
    return {name: _batch_sums(r, c) for name, c in cells.items()}


def _compare(world: World, plan: Plan, cells: dict[str, np.ndarray], n: int) -> None:
    """Dose runs with Woodcock and with the walk: ledgers close, nothing lost, the energy per
    history in every region agrees within 3σ, each to a few % (the comparison has teeth)."""
    runs = {}
    for tracking, seed in (("woodcock", 7), ("walk", 8)):
        r = simulate(world, plan, TransportSettings(n, 10, seed, electron_cutoff_mev=0.1,
                                                    photon_tracking=tracking), progress=False)
        _closes(r)
        assert r.record()["photon_tracking"] == tracking
        assert (r.record()["woodcock_steps"] > 0) == (tracking == "woodcock")
        runs[tracking] = _region_energy(r, cells)
    for name in cells:
        a, b = runs["woodcock"][name], runs["walk"][name]
        assert _z(a, b) < 3.0, (name, a, b)
        assert b[1] < 0.05 * b[0], (name, b)


def test_woodcock_dose_agrees_with_the_walk_on_a_water_lung_bone_tet_slab():
    mesh = _slab_mesh()
    z = mesh.centroids_mm[:, 2]
    central = np.all(np.abs(mesh.centroids_mm[:, :2]) < 10, axis=1)
    cells = {f"z {lo}-{hi}": (z > lo) & (z < hi) & central for lo, hi, _, _ in LAYERS}
    cells["outside the field"] = np.abs(mesh.centroids_mm[:, 0]) > 20
    _compare(World(mesh=mesh), Plan(SLAB_PLAN.beams, materials=MATERIALS), cells, 150_000)


def test_woodcock_dose_agrees_with_the_walk_on_the_hybrid_world():
    """The notched slab inside a CT of water, lung (0.26 in the notch's slab) and bone: per
    mesh layer, the notch's voxels, the CT before and behind the mesh."""
    mesh = _slab_mesh(notch=True)
    grid = helpers.grid_for((-40, -40, -10), (40, 40, 90), (5.0, 5.0, 5.0))
    ct = helpers.density_image(grid, lambda x, y, z: np.select([z < 20, z < 50, z < 70],
                                                               [1.0, 0.26, 1.0], 1.85))
    plan = Plan((PhotonSource("parallel", (0.0, 0.0, -15.0), (0, 0, 1), energies_mev=(2.0,),
                              field_mm=(50.0, 50.0)),), materials=MATERIALS)
    m = mesh.n_tets
    zt = mesh.centroids_mm[:, 2]
    c = grid.voxel_centers_mm()
    cells = {f"mesh z {lo}-{hi}": np.r_[(zt > lo) & (zt < hi), np.zeros(len(c), bool)]
             for lo, hi, _, _ in LAYERS}
    for name, sel in (("notch voxels", (c[:, 0] > 0) & (c[:, 1] > 0) & (c[:, 2] > 20)
                       & (c[:, 2] < 50)),
                      ("CT before", c[:, 2] < 0), ("CT behind", c[:, 2] > 80)):
        cells[name] = np.r_[np.zeros(m, bool), sel]
    _compare(World(mesh=mesh, density=ct), plan, cells, 150_000)


def test_woodcock_dose_agrees_with_the_walk_on_a_voxel_only_world():
    """The slab CT alone (water, lung, water, bone): dose per layer in and out of the field."""
    grid, ct = _slab_ct()
    plan = Plan((PhotonSource("parallel", (0.0, 0.0, -15.0), (0, 0, 1), energies_mev=(2.0,),
                              field_mm=(50.0, 50.0)),), materials=MATERIALS)
    c = grid.voxel_centers_mm()
    inside = np.all(np.abs(c[:, :2]) < 20, axis=1)
    cells = {f"z {lo}-{hi}": (c[:, 2] > lo) & (c[:, 2] < hi) & inside
             for lo, hi in ((-10, 20), (20, 50), (50, 70), (70, 90))}
    cells["outside the field"] = np.abs(c[:, 0]) > 30
    _compare(World(density=ct), plan, cells, 100_000)


@pytest.mark.slow
def test_woodcock_dose_agrees_with_the_walk_on_the_thorax_phantom():
    """A heterogeneous hybrid world: the medium thorax phantom's organ mesh (lungs, vessels,
    tumour; densities mapped from its CT) inside the CT, a 2 MeV and a 6 MeV beam at right angles:
    every mesh region and the voxels, energy per history, within 3σ of the walk (issue 20: the
    demo's γ fell when Woodcock tracking decorrelated its mesh and voxel runs; the doses did not
    move)."""
    from tetdose.core.calibration import HUCalibration
    from tetdose.core.image import Image
    from tetdose.mapping import map_density
    from tetdose.phantoms import make_phantom

    ph = make_phantom("thorax", seed=0, size="medium")
    cal = HUCalibration.schneider2000()
    mesh = map_density(ph.mesh, ph.ct, calibration=cal).mesh
    c = mesh.centroids_mm.mean(axis=0)
    plan = Plan((PhotonSource("parallel", [c[0] - 300.0, c[1], c[2]], [1, 0, 0],
                              energies_mev=[2.0], field_mm=[80.0, 80.0]),
                 PhotonSource("parallel", [c[0], c[1] - 300.0, c[2]], [0, 1, 0],
                              energies_mev=[6.0], field_mm=[60.0, 60.0])),
                materials=ph.materials)
    n_voxels = int(np.prod(ph.ct.grid.shape))
    cells = {f"region {g}": np.r_[mesh.region == g, np.zeros(n_voxels, bool)]
             for g in np.unique(mesh.region)}
    cells["voxels"] = np.r_[np.zeros(mesh.n_tets, bool), np.ones(n_voxels, bool)]
    world = World(mesh=mesh, density=Image(cal(ph.ct.array), ph.ct.grid), labels=ph.labels)
    _compare(world, plan, cells, 400_000)
