"""Transport verification: exp(−μL), exact free paths in a density gradient, energy ledger,
mesh vs voxel, analog vs track-length, σ ∝ N^-1/2, thread-count reproducibility, CLI."""

from __future__ import annotations

import itertools
import json
import math
import textwrap
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from tetdose._random import next_uniform, seed_for
from tetdose.core.image import Image, ImageGrid
from tetdose.core.io import read_image, read_mesh, write_image, write_mesh
from tetdose.core.mesh import TetMesh
from tetdose.transport import (
    PhotonSource,
    Plan,
    TransportSettings,
    mesh_geometry,
    simulate,
)
from tetdose.transport.geometry._tet import enter_mesh
from tetdose.transport.geometry._voxel import VoxelGeometry
from tetdose.transport.geometry._world import start_cell
from tetdose.transport.geometry.world import voxel_world
from tetdose.transport.history._photon import ESCAPES, INTERACTS, N_COUNTS, flight_mesh, flight_voxel
from tetdose.transport.physics._photon import transport_coefficients
from tetdose.transport.physics.xs import build_cross_sections

from helpers import same_bits_with_one_or_two_threads

REPO = Path(__file__).resolve().parents[2]
WATER_MU_RHO_1MEV = 0.07072  # NIST XCOM, cm²/g (total with coherent; coherent is 0.05 % of it)


def box_mesh(n, size_mm, origin_mm=(0.0, 0.0, 0.0)):
    """Structured box: n cubes per axis, each split into 6 tets (Kuhn subdivision).

    Cubes are numbered i-major and their 6 tets are consecutive: ``voxel_energy_from_mesh``
    relies on that order (tests/helpers.box_mesh numbers cubes z-major).
    """
    axes = [np.linspace(origin_mm[a], origin_mm[a] + size_mm[a], n[a] + 1) for a in range(3)]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    vid = lambda i, j, k: (i * (n[1] + 1) + j) * (n[2] + 1) + k  # noqa: E731
    tets = []
    for i, j, k in itertools.product(*(range(m) for m in n)):
        for perm in itertools.permutations(range(3)):
            c = [i, j, k]
            path = [vid(*c)]
            for a in perm:
                c[a] += 1
                path.append(vid(*c))
            tets.append(path)
    return TetMesh(pts, np.array(tets)).with_fixed_orientation()


def box_grid(n, size_mm, origin_mm=(0.0, 0.0, 0.0)):
    """The voxel grid whose voxels are exactly the cubes of ``box_mesh``."""
    spacing = np.array(size_mm) / np.array(n)
    return ImageGrid(np.array(origin_mm) + spacing / 2, spacing, np.eye(3), tuple(n))


def voxel_energy_from_mesh(energy_tets, n):
    """Sum the 6 tets of each cube (box_mesh order i, j, k) into flat voxel order (k, j, i)."""
    return energy_tets.reshape(*n, 6).sum(axis=3).transpose(2, 1, 0).reshape(-1)


@pytest.fixture(scope="module")
def xs():
    return build_cross_sections(["water"])


def _first_flights(flight, n, seed=7):
    """Outcomes and interaction points of n first flights (τ from the engine's generator)."""
    out, zs = np.empty(n, dtype=np.intp), np.empty(n)
    for h in range(n):
        _, xi = next_uniform(np.uint64(seed_for(seed, 0, h)))
        out[h], z = flight(-math.log(1.0 - xi))
        zs[h] = z
    return out, zs


@pytest.mark.parametrize("geometry", ["mesh", "voxel"])
def test_uncollided_fraction_is_exp_minus_mu_l(xs, geometry):
    """Pencil beam through 5 cm of water: P(no interaction) = exp(−μ/ρ·ρ·L), NIST μ/ρ."""
    n_hist, length_mm = 20_000, 50.0
    n = (3, 3, 5)
    if geometry == "mesh":
        mesh = box_mesh(n, (30.0, 30.0, length_mm), (-15.0, -15.0, 0.0))
        g = mesh_geometry(mesh, np.ones(mesh.n_points), np.zeros(mesh.n_tets, np.intp))
        k, x, y, z, _ = enter_mesh(g, 0.1, 0.2, -10.0, 0.0, 0.0, 1.0)
        tally, counts = np.zeros(mesh.n_tets), np.zeros(N_COUNTS, np.int64)

        def flight(tau):
            o, _, _, _, zz, _ = flight_mesh(g, xs, 1.0, k, -1, x, y, z, 0, 0, 1.0, tau, False,
                                            tally, counts)
            return o, zz
    else:
        grid = box_grid(n, (30.0, 30.0, length_mm), (-15.0, -15.0, 0.0))
        g = VoxelGeometry(-0.5 * grid.spacing_mm, grid.spacing_mm, np.array(n, np.intp),
                          np.ones(grid.n_voxels), np.zeros(grid.n_voxels, np.intp))
        q = grid.to_grid_frame(np.array([0.1, 0.2, -10.0]))
        wg = voxel_world(g)
        vid, x, y, z, _ = start_cell(wg, *q, 0.0, 0.0, 1.0)  # no mesh: cell = voxel id
        tally, counts = np.zeros(grid.n_voxels), np.zeros(N_COUNTS, np.int64)

        def flight(tau):
            o, _, _, _, zz, _ = flight_voxel(wg, xs, 1.0, vid, x, y, z, 0, 0, 1.0, tau, -1e-9,
                                             False, tally, counts)
            return o, zz
    out, _ = _first_flights(flight, n_hist)
    p = math.exp(-WATER_MU_RHO_1MEV * length_mm / 10.0)
    sigma = math.sqrt(p * (1 - p) / n_hist)
    assert abs(np.mean(out == ESCAPES) - p) < 4 * sigma


def test_linear_density_free_paths_are_exact(xs):
    """Density rising linearly with depth: transmission exp(−μ/ρ∫ρ ds) and the depth CDF."""
    n_hist, length_mm, rho0, rho1 = 20_000, 60.0, 0.3, 2.5
    mesh = box_mesh((2, 2, 4), (20.0, 20.0, length_mm), (-10.0, -10.0, 0.0))
    rho = rho0 + (rho1 - rho0) * mesh.points_mm[:, 2] / length_mm
    g = mesh_geometry(mesh, rho, np.zeros(mesh.n_tets, np.intp))
    k, x, y, z, _ = enter_mesh(g, 0.3, 0.1, -5.0, 0.0, 0.0, 1.0)
    tally, counts = np.zeros(mesh.n_tets), np.zeros(N_COUNTS, np.int64)
    out, depth = _first_flights(lambda tau: flight_mesh(
        g, xs, 1.0, k, -1, x, y, z, 0, 0, 1.0, tau, False, tally, counts)[:5:4], n_hist)
    mu = transport_coefficients(xs, 0, 1.0)[0]
    slope = (rho1 - rho0) / length_mm

    def tau(s):
        return mu * (rho0 * s + 0.5 * slope * s * s) / 10.0

    p = math.exp(-tau(length_mm))
    assert abs(np.mean(out == ESCAPES) - p) < 4 * math.sqrt(p * (1 - p) / n_hist)
    inside = depth[out == INTERACTS]
    cdf = lambda s: -np.expm1(-tau(np.asarray(s))) / (1.0 - p)  # noqa: E731
    assert stats.kstest(inside, cdf).pvalue > 1e-3


def _slab_mesh_with_regions():
    mesh = box_mesh((4, 4, 6), (40.0, 40.0, 60.0), (-20.0, -20.0, 0.0))
    z = mesh.centroids_mm[:, 2]
    region = np.where(z < 20, 1, np.where(z < 40, 2, 3))
    rho = np.where(mesh.points_mm[:, 2] < 30, 1.0, 0.3) + 0.01 * mesh.points_mm[:, 0]
    return TetMesh(mesh.points_mm, mesh.tets, region, {"density": rho})


ADVERSARIAL_PLAN = Plan(
    (PhotonSource("pencil", [0.0, 0.0, -30.0], [0, 0, 1], energies_mev=[6.0]),  # along edges
     PhotonSource("pencil", [-30.0, -30.0, -30.0], [1, 1, 1], energies_mev=[2.0]),  # diagonals
     PhotonSource("point", [0.0, 0.0, 30.0], energies_mev=[0.5, 3.0], line_weights=[1, 2],
                  weight=2.0),  # inside, isotropic, on a vertex
     PhotonSource("parallel", [0.0, 0.0, -5.0], [0, 0, 1], energies_mev=[10.0],
                  field_mm=[50.0, 50.0])),  # wider than the phantom: some photons miss
    materials={1: "water", 2: "lung"})


@pytest.mark.parametrize("estimator", ["analog", "track_length"])
def test_energy_ledger_closes_with_no_lost_photons(estimator):
    res = simulate(_slab_mesh_with_regions(), ADVERSARIAL_PLAN,
                   TransportSettings(4000, 4, 3, estimator=estimator, physics="kerma"), progress=False)
    led = res.ledger
    closing = led["deposited_mev"] + led["escaped_mev"] + led["cutoff_mev"] + led["lost_mev"]
    assert closing == pytest.approx(led["source_mev"], rel=1e-9)
    assert res.lost_photons == 0 and led["lost_mev"] == 0.0
    expected_mean_e = (6.0 + 2.0 + 2 * (0.5 + 2 * 3.0) / 3 + 10.0) / 5
    assert led["source_mev"] == pytest.approx(expected_mean_e, rel=0.05)
    if estimator == "analog":  # analog tally = deposited + cut off exactly
        total = res.energy_per_batch_mev.sum() / res.n_histories
        assert total == pytest.approx(led["deposited_mev"] + led["cutoff_mev"], rel=1e-9)


@pytest.fixture(scope="module")
def water_box():
    n, size, origin = (4, 4, 5), (40.0, 40.0, 50.0), (-20.0, -20.0, 0.0)
    mesh = box_mesh(n, size, origin)
    mesh = mesh.with_data(point_data={"density": np.ones(mesh.n_points)})
    grid = box_grid(n, size, origin)
    plan = Plan((PhotonSource("parallel", [0, 0, -10.0], [0, 0, 1], energies_mev=[1.25],
                              field_mm=[20.0, 20.0]),))
    return n, mesh, Image(np.ones(grid.shape), grid), plan


def _z(a, sa, b, sb):
    s = np.sqrt(sa**2 + sb**2)
    ok = (s > 0) & (a > 0) & (sa < 0.2 * a)
    return (a[ok] - b[ok]) / s[ok]


def test_mesh_and_voxel_dose_agree_on_homogeneous_water(water_box):
    n, mesh, image, plan = water_box
    settings = TransportSettings(20_000, 10, 5, physics="kerma")
    rm = simulate(mesh, plan, settings, progress=False)
    rv = simulate(image, plan, settings, progress=False)
    e_m = np.stack([voxel_energy_from_mesh(r, n) for r in rm.energy_per_batch_mev])
    mass = voxel_energy_from_mesh(rm.mass_g, n)
    np.testing.assert_allclose(mass, rv.mass_g, rtol=1e-12)
    x = e_m / rm.histories_per_batch[:, None]
    dm = x.mean(0) / mass
    sm = x.std(0, ddof=1) / math.sqrt(len(x)) / mass
    xv = rv.energy_per_batch_mev / rv.histories_per_batch[:, None]
    dv, sv = xv.mean(0) / rv.mass_g, xv.std(0, ddof=1) / math.sqrt(len(xv)) / rv.mass_g
    z = _z(dm, sm, dv, sv)
    assert len(z) > 20 and np.max(np.abs(z)) < 5.0 and abs(z.mean()) < 4 / math.sqrt(len(z))


def test_track_length_and_analog_agree(water_box):
    _, mesh, _, plan = water_box
    ra = simulate(mesh, plan, TransportSettings(20_000, 10, 11, estimator="analog", physics="kerma"),
                  progress=False)
    rt = simulate(mesh, plan, TransportSettings(20_000, 10, 12, estimator="track_length", physics="kerma"),
                  progress=False)
    ea = ra.energy_per_batch_mev.sum(1) / ra.histories_per_batch
    et = rt.energy_per_batch_mev.sum(1) / rt.histories_per_batch
    diff = ea.mean() - et.mean()
    sigma = math.sqrt(ea.var(ddof=1) / len(ea) + et.var(ddof=1) / len(et))
    assert abs(diff) < 4 * sigma
    z = _z(ra.dose_gy, ra.dose_std_gy, rt.dose_gy, rt.dose_std_gy)
    assert np.max(np.abs(z)) < 5.0
    # the kerma estimator is the less noisy one where the beam does not reach directly
    off_beam = np.abs(mesh.centroids_mm[:, 0]) > 12
    assert np.median(rt.relative_uncertainty[off_beam]) < np.median(
        ra.relative_uncertainty[off_beam])


def test_sigma_scales_as_inverse_sqrt_n(water_box):
    _, mesh, _, plan = water_box
    r1 = simulate(mesh, plan, TransportSettings(8_000, 40, 21, physics="kerma"), progress=False)
    r4 = simulate(mesh, plan, TransportSettings(32_000, 40, 22, physics="kerma"), progress=False)
    ok = (r1.relative_uncertainty > 0) & (r1.relative_uncertainty < 0.1)
    ratio = np.median(r1.dose_std_gy[ok] / r4.dose_std_gy[ok])
    assert ok.sum() > 50 and ratio == pytest.approx(2.0, rel=0.12)


def test_same_seed_one_or_two_threads_gives_identical_dose(tmp_path):
    same_bits_with_one_or_two_threads(tmp_path, Path(__file__).parent, """
        from test_transport import ADVERSARIAL_PLAN, _slab_mesh_with_regions
        from tetdose.transport import TransportSettings, simulate
        r = simulate(_slab_mesh_with_regions(), ADVERSARIAL_PLAN,
                     TransportSettings(3000, 6, 9, estimator="analog", physics="kerma"),
                     progress=False)
    """)


def _cli(argv):
    from tetdose.cli import main

    return main(["dose", "--physics", "kerma", *argv])


def test_cli_dose_on_mesh_and_on_ct(tmp_path, water_box):
    n, mesh, image, _ = water_box
    (tmp_path / "spectrum.csv").write_text("energy_mev,weight\n0.5,1\n1.5,3\n")
    (tmp_path / "plan.toml").write_text(textwrap.dedent("""
        [[beam]]
        type = "pencil"
        spectrum = "spectrum.csv"
        position_mm = [0.5, 0.5, -20.0]
        direction = [0.0, 0.0, 1.0]
        [materials]
        1 = "water"
        [normalization]
        particles = 1e9
    """))
    write_mesh(tmp_path / "mapped.vtu", TetMesh(mesh.points_mm, mesh.tets,
                                                np.ones(mesh.n_tets, int), mesh.point_data))
    hu = np.zeros(image.grid.shape)  # water-like CT: 0 HU
    write_image(tmp_path / "ct.nrrd", Image(hu.astype(np.int16), image.grid))
    common = ["--plan", str(tmp_path / "plan.toml"), "--histories", "2e3", "--seed", "4", "-q"]
    assert _cli(["--mesh", str(tmp_path / "mapped.vtu"), "-o", str(tmp_path / "dose.vtu"),
                 *common]) == 0
    rec = json.loads((tmp_path / "dose.json").read_text())
    with pytest.warns(UserWarning, match="no region labels"):
        assert _cli(["--ct", str(tmp_path / "ct.nrrd"), "-o", str(tmp_path / "dose.nrrd"),
                     *common]) == 0
    out_mesh = read_mesh(tmp_path / "dose.vtu")
    assert rec["histories"] == 2000 and rec["seed"] == 4 and rec["lost_photons"] == 0
    assert rec["ledger"]["source_mev"] == pytest.approx(1.25, rel=0.05)
    assert np.all(out_mesh.cell_data["dose"] >= 0)
    # the record's near-maximum: D0.1cm³ over the tets (all water), not above the hottest tet
    hottest = np.sort(out_mesh.cell_data["dose"])[::-1]
    assert hottest[-1] <= rec["near_max_dose_gy"] <= hottest[0] and "D0.1cm³" in rec["near_max"]
    assert np.all(out_mesh.cell_data["dose_std"] >= 0)
    dose = read_image(tmp_path / "dose.nrrd")
    std = read_image(tmp_path / "dose_std.nrrd")
    assert dose.grid.same_as(image.grid) and std.array.shape == dose.array.shape
    # both engines: most dose on the beam axis column (pencil at x, y ≈ 0)
    col = dose.array[:, 1:3, 1:3].sum()
    assert col > 0.5 * dose.array.sum()
    assert json.loads((tmp_path / "dose.json").read_text())["geometry"] == "voxel"
