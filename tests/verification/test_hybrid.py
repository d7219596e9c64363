"""The hybrid world (a mesh inside a CT) against independent references: the voxel engine on the
same CT, the mesh engine on a mesh that fills the CT, and voxel twins of meshes in vacuum.

Each comparison uses another random stream for the reference, so the two runs are independent
and a z-test on batch statistics is meaningful (the same stream gives nearly the same photons).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from tetdose.core.image import Image
from tetdose.core.mesh import TetMesh
from tetdose.transport import PhotonSource, Plan, TransportSettings, World, simulate

from helpers import box_mesh, density_image, grid_for

LUNG, BONE = 0.26, 1.85
SLAB_PLAN = Plan((PhotonSource("parallel", [0.0, 0.0, -40.0], [0, 0, 1], energies_mev=[1.25],
                               field_mm=[60.0, 60.0]),))


def _settings(n, stream, estimator="track_length", seed=3):
    return TransportSettings(n, 10, seed, estimator=estimator, stream=stream, physics="kerma")


def _batch_sums(result, cells):
    """(mean, σ) of the energy per history summed over ``cells`` (from the batch spread)."""
    x = result.energy_per_batch_mev[:, cells].sum(axis=1) / result.histories_per_batch
    return x.mean(), x.std(ddof=1) / math.sqrt(len(x))


def _z(a, b):
    return abs(a[0] - b[0]) / math.hypot(a[1], b[1])


def _slab_world():
    """Water | lung | bone slabs along z (50 mm each, 5 mm voxels); the lung slab is meshed with
    faces on voxel planes and reaching the CT's lateral outer faces (the adversarial case)."""
    grid = grid_for((-50, -50, 0), (50, 50, 150), (5.0, 5.0, 5.0))
    ct = density_image(grid, lambda x, y, z: np.select([z < 50, z < 100], [1.0, LUNG], BONE))
    mesh = box_mesh((-50, -50, 50), (50, 50, 100), (4, 4, 2))
    mesh = mesh.with_data(point_data={"density": np.full(mesh.n_points, LUNG)})
    return mesh, ct


def _ledger_closes(result):
    led = result.ledger
    total = led["deposited_mev"] + led["escaped_mev"] + led["cutoff_mev"] + led["lost_mev"]
    assert total == pytest.approx(led["source_mev"], rel=1e-9)
    assert result.lost_photons == 0


@pytest.fixture(scope="module")
def slab_runs():
    mesh, ct = _slab_world()
    hybrid = simulate(World(mesh=mesh, density=ct), SLAB_PLAN, _settings(20_000, 0),
                      progress=False)
    voxel = simulate(ct, SLAB_PLAN, _settings(20_000, 1), progress=False)
    return mesh, ct, hybrid, voxel


def test_hybrid_equals_voxels_per_slab(slab_runs):
    mesh, ct, hybrid, voxel = slab_runs
    z = ct.grid.voxel_centers_mm()[:, 2]
    m = mesh.n_tets
    slabs = [z < 50, (z >= 50) & (z < 100), z >= 100]
    for i, sl in enumerate(slabs):
        ref = _batch_sums(voxel, np.flatnonzero(sl))
        if i == 1:
            got = _batch_sums(hybrid, np.arange(m))  # the lung slab is all mesh
            assert hybrid.mass_g[m:][sl].max() < 1e-12  # its voxels carry no voxel mass
        else:
            got = _batch_sums(hybrid, m + np.flatnonzero(sl))
        assert ref[0] > 0 and _z(got, ref) < 4, (i, got, ref)
    _ledger_closes(hybrid)
    assert hybrid.record()["mesh_voxel_switches"] > 0


def _z_per_cell(e1, e2, n1, n2):
    """z of the per-cell means of two sets of batch rows (energy per history), for the cells
    holding ≥ 20 % of the largest mean (well-sampled: the batch spread is near Gaussian)."""
    x1, x2 = e1 / n1[:, None], e2 / n2[:, None]
    s = np.hypot(x1.std(axis=0, ddof=1) / math.sqrt(len(x1)), x2.std(axis=0, ddof=1)
                 / math.sqrt(len(x2)))
    ok = (s > 0) & (x2.mean(axis=0) > 0.2 * x2.mean(axis=0).max())
    return (x1.mean(axis=0)[ok] - x2.mean(axis=0)[ok]) / s[ok]


def test_combined_dose_image_equals_voxel_dose(slab_runs):
    """Outside the mesh voxel by voxel; inside, tet by tet against the voxel run's energy moved
    onto the tets by exact overlap volumes (matched resolution: the mesh's tets are larger)."""
    from tetdose.core.overlap import compute_overlap

    mesh, ct, hybrid, voxel = slab_runs
    m = mesh.n_tets
    comb = hybrid.combined()
    # mass: mesh part + voxel part = CT mass voxel by voxel (the mesh density equals the CT's)
    ct_mass = ct.array.ravel() * ct.grid.voxel_volume_mm3 / 1000.0
    np.testing.assert_allclose(comb.mass_g, ct_mass, rtol=1e-9)
    assert comb.energy_mev.sum() == pytest.approx(hybrid.energy_mev.sum(), rel=1e-12)
    outside = np.flatnonzero(hybrid.mass_g[m:] > 0)
    z_vox = _z_per_cell(hybrid.energy_per_batch_mev[:, m + outside],
                        voxel.energy_per_batch_mev[:, outside], hybrid.histories_per_batch,
                        voxel.histories_per_batch)
    share = compute_overlap(mesh, ct.grid).volume_matrix_mm3() / ct.grid.voxel_volume_mm3
    z_tet = _z_per_cell(hybrid.energy_per_batch_mev[:, :m],
                        (share @ voxel.energy_per_batch_mev.T).T, hybrid.histories_per_batch,
                        voxel.histories_per_batch)
    for zz in (z_vox, z_tet):
        assert len(zz) > 50 and np.mean(np.abs(zz) > 4) < 0.01 and np.std(zz) < 1.3
    dose, _ = hybrid.to_images()
    np.testing.assert_array_equal(dose.array.ravel(), comb.dose_gy)
    assert dose.grid.same_as(ct.grid)


def _ball_mesh(radius_mm, n):
    """A ball: the cube [−1, 1]³ (n³ cells, 6 Kuhn tets each) mapped radially, p ↦ r·p·|p|∞/|p|₂."""
    cube = box_mesh((-1, -1, -1), (1, 1, 1), (n, n, n))
    p = cube.points_mm
    norm2 = np.linalg.norm(p, axis=1)
    scale = np.divide(np.abs(p).max(axis=1), norm2, out=np.ones(len(p)), where=norm2 > 0)
    return TetMesh(radius_mm * p * scale[:, None], cube.tets).with_fixed_orientation()


def test_curved_mesh_in_a_rotated_ct_equals_voxels():
    """A water ball meshed inside a water CT whose grid is rotated 30° about z (frames matter)."""
    c, s = math.cos(math.radians(30)), math.sin(math.radians(30))
    rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    grid = grid_for((-60, -60, -60), (60, 60, 60), (6.0, 6.0, 6.0), direction=rot)
    grid = type(grid)(rot @ (grid.origin_mm), grid.spacing_mm, rot, grid.size)  # centred on 0
    ct = Image(np.ones(grid.shape), grid)
    ball = _ball_mesh(35.0, 6)
    ball = ball.with_data(point_data={"density": np.ones(ball.n_points)})
    ball.check_cells()
    plan = Plan((PhotonSource("point", [0.0, 0.0, -150.0], [0, 0, 1], energies_mev=[0.8],
                              half_angle_deg=12.0),))
    hybrid = simulate(World(mesh=ball, density=ct), plan, _settings(20_000, 0), progress=False)
    voxel = simulate(ct, plan, _settings(20_000, 1), progress=False)
    _ledger_closes(hybrid)
    assert _z(_batch_sums(hybrid, slice(None)), _batch_sums(voxel, slice(None))) < 4
    outside = np.flatnonzero(hybrid.mass_g[ball.n_tets:] > 0.99 * 0.216)  # uncut voxels
    zz = _z_per_cell(hybrid.energy_per_batch_mev[:, ball.n_tets + outside],
                     voxel.energy_per_batch_mev[:, outside], hybrid.histories_per_batch,
                     voxel.histories_per_batch)
    assert len(zz) > 100 and np.mean(np.abs(zz) > 4) < 0.01 and np.std(zz) < 1.3


def test_mesh_filling_the_ct_equals_the_mesh_alone():
    grid = grid_for((-40, -40, 0), (40, 40, 80), (8.0, 8.0, 8.0))
    ct = Image(np.full(grid.shape, 1.0), grid)
    mesh = box_mesh((-40, -40, 0), (40, 40, 80), (4, 4, 4), jitter=0.2, seed=2)
    mesh = mesh.with_data(point_data={"density": 1.0 + 0.01 * mesh.points_mm[:, 2]})
    plan = Plan((PhotonSource("parallel", [0, 0, -30.0], [0, 0, 1], energies_mev=[1.0],
                              field_mm=[50, 50]),))
    hybrid = simulate(World(mesh=mesh, density=ct), plan, _settings(20_000, 0), progress=False)
    alone = simulate(mesh, plan, _settings(20_000, 1), progress=False)
    assert hybrid.mass_g[mesh.n_tets:].max() < 1e-9  # every voxel is wholly covered
    # photons leaving through the CT's outer face cross a voxel only by rounding (≤ 1e-15 mm)
    assert hybrid.energy_mev[mesh.n_tets:].sum() < 1e-12 * hybrid.energy_mev.sum()
    a, b = hybrid.mesh_part(), alone
    ok = (a.dose_std_gy > 0) & (b.dose_std_gy > 0)
    zz = (a.dose_gy[ok] - b.dose_gy[ok]) / np.hypot(a.dose_std_gy[ok], b.dose_std_gy[ok])
    assert ok.sum() > 100 and np.mean(np.abs(zz) > 4) < 0.01
    assert _z(_batch_sums(a, slice(None)), _batch_sums(b, slice(None))) < 4
    _ledger_closes(hybrid)


def _union(*meshes):
    pts, tets, off = [], [], 0
    for m in meshes:
        pts.append(m.points_mm)
        tets.append(m.tets + off)
        off += m.n_points
    mesh = TetMesh(np.concatenate(pts), np.concatenate(tets))
    return mesh.with_data(point_data={"density": np.ones(mesh.n_points)})


def _twin_grid(mesh, lo, hi, spacing, inside):
    """Voxel twin of a mesh in vacuum: density 1 where ``inside(x, y, z)``, 0 elsewhere."""
    grid = grid_for(lo, hi, (spacing,) * 3)
    return density_image(grid, lambda x, y, z: np.where(inside(x, y, z), 1.0, 0.0))


def test_two_disjoint_cubes_photons_re_enter_the_mesh():
    """Isotropic 1 MeV source in cube A: cube B, 100 mm away, gets the voxel twin's energy."""
    a = box_mesh((-150, -50, -50), (-50, 50, 50), (4, 4, 4))
    b = box_mesh((50, -50, -50), (150, 50, 50), (4, 4, 4))
    mesh = _union(a, b)
    twin = _twin_grid(mesh, (-150, -50, -50), (150, 50, 50), 10.0,
                      lambda x, y, z: np.abs(x) > 50)
    plan = Plan((PhotonSource("point", [-100.0, 0, 0], [1, 0, 0], energies_mev=[1.0]),))
    res = simulate(mesh, plan, _settings(20_000, 0), progress=False)
    ref = simulate(twin, plan, _settings(20_000, 1), progress=False)
    in_b = np.flatnonzero(mesh.centroids_mm[:, 0] > 0)
    vox_b = np.flatnonzero(twin.grid.voxel_centers_mm()[:, 0] > 0)
    got, want = _batch_sums(res, in_b), _batch_sums(ref, vox_b)
    assert got[0] > 0 and want[0] > 0 and _z(got, want) < 4, (got, want)
    _ledger_closes(res)


def test_mesh_reaching_beyond_the_ct_meets_vacuum_there():
    """Two cubes, the CT covers only cube A (and 10 mm of water around it): photons leave the
    grid and still reach cube B beyond it; B gets what it gets with the world = mesh + twin."""
    a = box_mesh((-150, -50, -50), (-50, 50, 50), (4, 4, 4))
    b = box_mesh((50, -50, -50), (150, 50, 50), (4, 4, 4))
    mesh = _union(a, b)
    ct = _twin_grid(mesh, (-160, -60, -60), (-40, 60, 60), 10.0, lambda x, y, z: x < 1e9)
    twin = _twin_grid(mesh, (-160, -60, -60), (150, 60, 60), 10.0,
                      lambda x, y, z: (x < -40) | ((x > 50) & (np.abs(y) < 50) & (np.abs(z) < 50)))
    plan = Plan((PhotonSource("point", [-100.0, 0, 0], [1, 0, 0], energies_mev=[1.0]),))
    with pytest.warns(UserWarning, match="outside the CT grid"):
        res = simulate(World(mesh=mesh, density=ct), plan, _settings(20_000, 0), progress=False)
    ref = simulate(twin, plan, _settings(20_000, 1), progress=False)
    got = _batch_sums(res, np.flatnonzero(mesh.centroids_mm[:, 0] > 0))
    want = _batch_sums(ref, np.flatnonzero(twin.grid.voxel_centers_mm()[:, 0] > 0))
    assert got[0] > 0 and _z(got, want) < 4, (got, want)
    _ledger_closes(res)


def test_concave_u_mesh_re_entry_matches_its_voxel_twin():
    """A U (three 40 mm columns, the middle one half height): a beam from the left arm across the
    notch deposits in the right arm what the voxel twin deposits there."""
    cells = box_mesh((-60, -20, 0), (60, 20, 80), (3, 1, 2))
    keep = np.ones(cells.n_tets, bool)
    keep[6 * (1 * 3 + 1):6 * (1 * 3 + 1) + 6] = False  # cell (i=1, k=1): the notch
    u = _union(TetMesh(cells.points_mm, cells.tets[keep]))
    twin = _twin_grid(u, (-60, -20, 0), (60, 20, 80), 10.0,
                      lambda x, y, z: ~((np.abs(x) < 20) & (z > 40)))
    plan = Plan((PhotonSource("parallel", [-80.0, 0, 60], [1, 0, 0], energies_mev=[0.5],
                              field_mm=[30, 30]),))
    res = simulate(u, plan, _settings(20_000, 0), progress=False)
    ref = simulate(twin, plan, _settings(20_000, 1), progress=False)
    right = np.flatnonzero(u.centroids_mm[:, 0] > 20)
    vox_right = np.flatnonzero(twin.grid.voxel_centers_mm()[:, 0] > 20)
    got, want = _batch_sums(res, right), _batch_sums(ref, vox_right)
    assert got[0] > 0 and _z(got, want) < 4, (got, want)


def test_rays_along_voxel_edges_mesh_vertices_and_faces_are_never_lost():
    """10⁶ histories on the slab world: pencils along voxel edges through mesh vertices, a pencil
    lying in the mesh/voxel interface plane, and an isotropic source on an interface vertex."""
    mesh, ct = _slab_world()
    world = World(mesh=mesh, density=ct)
    beams = (PhotonSource("pencil", [0.0, 0.0, -10.0], [0, 0, 1], energies_mev=[1.0]),
             PhotonSource("pencil", [-25.0, 25.0, -10.0], [0, 0, 1], energies_mev=[1.0]),
             PhotonSource("pencil", [-60.0, 0.0, 50.0], [1, 0, 0], energies_mev=[1.0]),
             PhotonSource("pencil", [-60.0, 25.0, 100.0], [1, 0, 0], energies_mev=[1.0]),
             PhotonSource("point", [0.0, 0.0, 50.0], [0, 0, 1], energies_mev=[1.0]))
    res = simulate(world, Plan(beams),
                   TransportSettings(1_000_000, 10, 5, estimator="analog", physics="kerma"),
                   progress=False)
    _ledger_closes(res)
    rec = res.record()
    assert rec["mesh_voxel_switches"] > 100_000
    assert rec["relocations"] < 1e-3 * 1_000_000  # counted and reported, rare


def test_same_seed_same_bits_for_the_hybrid_with_one_or_two_threads(tmp_path):
    from pathlib import Path

    from helpers import same_bits_with_one_or_two_threads

    same_bits_with_one_or_two_threads(tmp_path, Path(__file__).parent, """
        from test_hybrid import SLAB_PLAN, _slab_world
        from tetdose.transport import TransportSettings, World, simulate
        mesh, ct = _slab_world()
        r = simulate(World(mesh=mesh, density=ct), SLAB_PLAN,
                     TransportSettings(4000, 8, 9, physics="kerma"), progress=False)
    """)


def test_cli_dose_on_mesh_inside_ct_then_compare(tmp_path):
    """`tetdose dose --mesh --ct` writes the mesh part, the combined and the voxel-part images
    and the record; `compare` says which region it used."""
    import json
    import textwrap

    from tetdose.cli import main
    from tetdose.core.calibration import HUCalibration
    from tetdose.core.io import read_image, read_mesh, write_image, write_mesh

    grid = grid_for((-40, -40, -40), (40, 40, 40), (5.0, 5.0, 5.0))
    write_image(tmp_path / "ct.nrrd", Image(np.zeros(grid.shape, np.int16), grid))
    rho_water = float(HUCalibration.schneider2000().density(np.array([0.0]))[0])
    mesh = box_mesh((-20, -20, -20), (20, 20, 20), (3, 3, 3), jitter=0.2, seed=4)
    write_mesh(tmp_path / "mapped.vtu",
               mesh.with_data(point_data={"density": np.full(mesh.n_points, rho_water)}))
    (tmp_path / "plan.toml").write_text(textwrap.dedent("""
        [[beam]]
        type = "parallel"
        energy_mev = 1.25
        position_mm = [0.0, 0.0, -60.0]
        direction = [0.0, 0.0, 1.0]
        field_mm = [50.0, 50.0]
    """))
    common = ["--plan", str(tmp_path / "plan.toml"), "--histories", "4e3", "--seed", "2", "-q"]
    assert main(["dose", "--physics", "kerma",
                 "--mesh", str(tmp_path / "mapped.vtu"), "--ct", str(tmp_path / "ct.nrrd"),
                 "-o", str(tmp_path / "dose.vtu"), *common]) == 0
    assert main(["dose", "--physics", "kerma",
                 "--ct", str(tmp_path / "ct.nrrd"), "-o", str(tmp_path / "vox.nrrd"),
                 *common]) == 0
    rec = json.loads((tmp_path / "dose.json").read_text())
    assert rec["world"] == "hybrid" and rec["lost_photons"] == 0 and rec["n_tets"] == mesh.n_tets
    assert rec["n_voxels"] == grid.n_voxels and rec["mesh_voxel_switches"] > 0
    tets = read_mesh(tmp_path / "dose.vtu").cell_data["dose"]
    comb, part = read_image(tmp_path / "dose.nrrd"), read_image(tmp_path / "dose_voxels.nrrd")
    assert comb.grid.same_as(grid) and (tmp_path / "dose_std.nrrd").exists()
    inside = np.all(np.abs(grid.voxel_centers_mm()) < 20, axis=1).reshape(grid.shape)
    assert np.all(part.array[inside] == 0) and comb.array[inside].min() > 0 and tets.max() > 0
    assert main(["compare", "--mesh-dose", str(tmp_path / "dose.vtu"), "--voxel-dose",
                 str(tmp_path / "vox.nrrd"), "-o", str(tmp_path / "cmp"), "-q"]) == 0
    summary = json.loads((tmp_path / "cmp" / "summary.json").read_text())
    assert summary["region"]["voxels"] == int(inside.sum())
    assert summary["region"]["volume_cm3"] == pytest.approx(40.0**3 / 1000.0)


def test_beams_that_miss_the_world_are_refused_and_long_runs_announced(tmp_path):
    """A beam aimed away from the mesh and the CT is an error before the run; a run estimated
    above LONG_RUN_S is announced with its estimated duration, one above MAX_RUN_S refused."""
    from tetdose.errors import PlanError
    from tetdose.transport.run import job

    mesh, ct = _slab_world()
    away = Plan((PhotonSource("pencil", [0.0, 0.0, -40.0], [0, 0, -1], energies_mev=[1.0]),))
    with pytest.raises(PlanError, match="miss"):
        simulate(World(mesh=mesh, density=ct), away, _settings(2000, 0), progress=False)
    with pytest.raises(PlanError, match="miss"):
        simulate(mesh, away, _settings(2000, 0), progress=False)
    long, endless = _settings(10**10, 0), _settings(10**13, 0)  # hours to days; centuries
    jb, _ = job.build_job(World(mesh=mesh, density=ct), SLAB_PLAN, long)
    with pytest.warns(UserWarning, match=r"will take about .* \(.*µs per history"):
        estimate = job.preflight(jb, job.cross_sections(jb, long), long, 2)
    assert job.LONG_RUN_S < estimate < job.MAX_RUN_S
    with pytest.raises(PlanError, match="would take about"):
        job.preflight(jb, job.cross_sections(jb, endless), endless, 2)
