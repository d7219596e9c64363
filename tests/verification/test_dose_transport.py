"""Dose mode (coupled electron transport) verification: the energy ledger closes and nothing is
lost on the adversarial meshes and the hybrid world, one or two threads give the same bits, a
straight CSDA track stops at the ESTAR range in voxels and in a linear-density mesh, mesh and
voxel doses agree on a homogeneous box, and a photon beam builds up its dose under the surface."""

from __future__ import annotations

import json
import math
import textwrap
from pathlib import Path

import numpy as np
import pytest
from numba import njit
from test_hybrid import _slab_world
from test_transport import ADVERSARIAL_PLAN, _slab_mesh_with_regions

from tetdose._random import seed_for
from tetdose.core.image import Image, ImageGrid
from tetdose.core.mesh import TetMesh
from tetdose.transport import PhotonSource, Plan, TransportSettings, World, simulate
from tetdose.transport.geometry._voxel import VoxelGeometry
from tetdose.transport.geometry._world import WorldGeometry
from tetdose.transport.geometry.tets import mesh_geometry
from tetdose.transport.geometry.world import voxel_world
from tetdose.transport.history._electron import (
    N_COUNTS_DOSE,
    N_LEDGER_DOSE,
    STACK_COLUMNS,
    WaterTally,
    electron_track,
)
from tetdose.transport.physics.electron_xs import (
    build_electron_tables,
    collision_stopping_power,
    csda_range_g_cm2,
    radiative_stopping_power,
)

import helpers
from helpers import same_bits_with_one_or_two_threads

#: NIST ESTAR CSDA range of 1 MeV electrons in liquid water [g/cm²] (NIST SRD 124).
ESTAR_WATER_1MEV_G_CM2 = 0.4367

CHARGED = (PhotonSource("pencil", [0.0, 0.0, -30.0], [0, 0, 1], energies_mev=[6.0],
                        particle="electron"),  # along mesh edges, through vertices
           PhotonSource("pencil", [-30.0, -30.0, -30.0], [1, 1, 1], energies_mev=[2.0],
                        particle="positron"),  # along cube diagonals
           PhotonSource("point", [0.0, 0.0, 30.0], energies_mev=[0.5, 3.0],
                        line_weights=[1, 2], particle="electron"))  # on a vertex, isotropic


def _closes(result):
    led = result.ledger
    rest = sum(v for k, v in led.items() if k != "source_mev")
    assert rest == pytest.approx(led["source_mev"], rel=1e-9)
    local = (led["deposited_mev"] + led["cutoff_mev"] + led["electron_deposited_mev"]
             + led["electron_cutoff_mev"])
    assert result.absorbed_mev == pytest.approx(local, rel=1e-12)
    assert result.escaped_mev == pytest.approx(led["escaped_mev"] + led["electron_escaped_mev"],
                                               rel=1e-12)
    assert result.energy_per_batch_mev.sum() / result.n_histories == pytest.approx(
        result.absorbed_mev, rel=1e-9)
    assert result.lost_photons == 0 and led["lost_mev"] == 0.0


def test_dose_mode_ledger_closes_and_nothing_is_lost_on_the_adversarial_mesh():
    plan = Plan(ADVERSARIAL_PLAN.beams + CHARGED, materials={1: "water", 2: "lung"})
    res = simulate(_slab_mesh_with_regions(), plan,
                   TransportSettings(6000, 4, 3, electron_cutoff_mev=0.05), progress=False)
    _closes(res)
    rec = res.record()
    assert rec["physics"] == "dose" and rec["estimator"] == "analog"
    assert rec["electron_cutoff_mev"] == 0.05 and rec["photon_cutoff_mev"] == 0.01
    assert rec["electron_steps"] > rec["electron_tracks"] > 1000
    assert res.ledger["electron_escaped_mev"] > 0.0  # the 6 MeV electrons leave the slab
    assert rec["photon_tracking"] == "woodcock" and rec["woodcock_steps"] > 1000


def test_dose_mode_on_the_hybrid_world_along_voxel_edges_and_mesh_faces():
    """Photon and electron pencils along voxel edges through mesh vertices and in the mesh/voxel
    interface plane, and an isotropic source on an interface vertex (test_hybrid's slab world)."""
    mesh, ct = _slab_world()
    beams = []
    for particle, e in (("photon", 2.0), ("electron", 3.0)):
        beams += [PhotonSource("pencil", [0.0, 0.0, -10.0], [0, 0, 1], energies_mev=[e],
                               particle=particle),
                  PhotonSource("pencil", [-25.0, 25.0, 45.0], [0, 0, 1], energies_mev=[e],
                               particle=particle),
                  PhotonSource("pencil", [-60.0, 25.0, 100.0], [1, 0, 0], energies_mev=[e],
                               particle=particle),
                  PhotonSource("point", [0.0, 0.0, 50.0], [0, 0, 1], energies_mev=[e],
                               particle=particle)]
    res = simulate(World(mesh=mesh, density=ct), Plan(tuple(beams)),
                   TransportSettings(40_000, 4, 5, electron_cutoff_mev=0.05), progress=False)
    _closes(res)
    rec = res.record()
    assert rec["mesh_voxel_switches"] > 1000
    assert rec["relocations"] < 1e-3 * 40_000
    assert rec["woodcock_steps"] > 1000  # the photons cross the mesh by Woodcock tracking


def test_dose_mode_same_seed_same_bits_with_one_or_two_threads(tmp_path):
    same_bits_with_one_or_two_threads(tmp_path, Path(__file__).parent, """
        from test_dose_transport import CHARGED
        from test_hybrid import SLAB_PLAN, _slab_world
        from tetdose.plan.volume_source import VolumeSource
        from tetdose.transport import Plan, TransportSettings, World, simulate
        mesh, ct = _slab_world()
        plan = Plan(SLAB_PLAN.beams + CHARGED,
                    volume_sources=(VolumeSource("positron", (1.0,)),))
        r = simulate(World(mesh=mesh, density=ct), plan,
                     TransportSettings(3000, 8, 9, electron_cutoff_mev=0.05, dose_to="water"),
                     progress=False)  # D_w: the tracked dose-to-water sums in batch order too
    """)


def _csda_tables(cutoff_mev=0.001):
    """Water tables for a straight CSDA track: the unrestricted total stopping power and CSDA
    range (above the cut-off), no hard events, no elastic scattering."""
    et = build_electron_tables(["water"], cutoff_mev=cutoff_mev, photon_cutoff_mev=cutoff_mev)
    t = np.exp(et.ln_e_min + et.d_ln_e * np.arange(et.stopping.shape[2]))
    s = np.empty_like(et.stopping)
    r = np.empty_like(et.range_g_cm2)
    for sp in (0, 1):
        s[0, sp] = (collision_stopping_power("water", sp, t)
                    + radiative_stopping_power("water", sp, t))
        r[0, sp] = csda_range_g_cm2("water", t, sp) - csda_range_g_cm2(
            "water", np.array([cutoff_mev]), sp)[0]
    r[:, :, 0] = 0.0
    zero = np.zeros_like(et.sigma_delta)
    return et._replace(stopping=s, range_g_cm2=r, sigma_delta=zero, sigma_brems=zero.copy(),
                       sigma_annih=np.zeros_like(et.sigma_annih), lambda1_inv=zero.copy(),
                       lambda2_inv=zero.copy())


@njit(cache=True)
def _one_track(wg, et, e, cell, x, y, z, w, n_cells):
    """Energy per cell of one electron started at (x, y, z) in ``cell`` along (0, 0, w)."""
    tally = np.zeros(n_cells)
    ledger = np.zeros(N_LEDGER_DOSE)
    counts = np.zeros(N_COUNTS_DOSE, np.int64)
    stack = np.empty((8, STACK_COLUMNS))
    bcell, bcol = np.empty(256, np.intp), np.empty(256)
    sig_hat = np.zeros((1, 2, et.stopping.shape[2]))
    dw = WaterTally(np.zeros((2, 0)), np.zeros(0), np.zeros(0))
    electron_track(wg, et, sig_hat, 0, e, cell, x, y, z, 0.0, 0.0, w, 1.0, seed_for(1, 0, 0), 0.25,
                   tally, ledger, counts, stack, 0, bcell, bcol, dw)
    return tally, ledger


def test_straight_csda_track_stops_at_the_estar_range_in_voxels_and_linear_density_tets():
    """Without hard events and deflections a 1 MeV electron runs its CSDA range: the column
    density from its start to the cell of its last deposit is the ESTAR 0.4367 g/cm² (within
    1 % and the cell size), in 0.01 mm voxels of water and in tets whose density rises
    linearly along the track (the column is then ∫ρ dz, solved exactly by the walker)."""
    et = _csda_tables()
    # voxels: a column of 1 × 1 × 0.01 mm³ water voxels along z
    n = 600
    vox = VoxelGeometry(np.array([-0.5, -0.5, -0.005]), np.array([1.0, 1.0, 0.01]),
                        np.array([1, 1, n], np.intp), np.ones(n), np.zeros(n, np.intp))
    tally, ledger = _one_track(voxel_world(vox), et, 1.0, 0, 0.0, 0.0, -0.005, 1.0, n)
    last = np.flatnonzero(tally)[-1]
    depth_g_cm2 = (last + 0.5) * 0.01 / 10.0
    assert tally.sum() == pytest.approx(1.0, rel=1e-12) and ledger[6] == 0.0  # nothing escaped
    assert depth_g_cm2 == pytest.approx(ESTAR_WATER_1MEV_G_CM2, rel=0.01)
    # tets: ρ(z) = 0.5 + 0.2 z [g/cm³, z in mm] along the track, layers 0.02 mm thick
    mesh = helpers.box_mesh((-0.5, -0.5, 0.0), (0.5, 0.5, 8.0), (1, 1, 400))
    rho = 0.5 + 0.2 * mesh.points_mm[:, 2]
    g = mesh_geometry(mesh, rho, np.zeros(mesh.n_tets, np.intp))
    empty = VoxelGeometry(np.zeros(3), np.ones(3), np.zeros(3, np.intp), np.zeros(0),
                          np.zeros(0, np.intp))
    z3 = np.zeros(3, np.intp)
    wg = WorldGeometry(g, empty, z3, z3.copy(), np.zeros(1, np.intp), np.zeros(0, np.intp))
    start = int(np.argmin(np.linalg.norm(mesh.centroids_mm - [0.1, 0.2, 0.01], axis=1)))
    p = mesh.centroids_mm[start]
    tally, _ = _one_track(wg, et, 1.0, start, p[0], p[1], p[2], 1.0, mesh.n_tets)
    z_last = mesh.centroids_mm[np.flatnonzero(tally), 2].max()
    column = lambda z: (0.5 * z + 0.1 * z * z) / 10.0  # noqa: E731  ∫ρ dz [g/cm²]
    assert column(z_last) - column(p[2]) == pytest.approx(ESTAR_WATER_1MEV_G_CM2, rel=0.01)
    assert tally.sum() == pytest.approx(1.0, rel=1e-12)


def test_mesh_and_voxel_dose_agree_for_an_electron_beam_in_water():
    """A 4 MeV electron beam in a water box: the energy in each cube's 6 tets equals the energy
    in the same voxel (same physics, two walkers; independent seeds) within statistics."""
    n, size = (6, 6, 6), (30.0, 30.0, 30.0)
    mesh = helpers.box_mesh((0, 0, 0), size, n)
    mesh = TetMesh(mesh.points_mm, mesh.tets, np.ones(mesh.n_tets, int),
                   {"density": np.ones(mesh.n_points)})
    spacing = np.array(size) / n
    grid = ImageGrid(spacing / 2, spacing, np.eye(3), n)
    plan = Plan((PhotonSource("parallel", [15.0, 15.0, -5.0], [0, 0, 1], energies_mev=[4.0],
                              field_mm=[20.0, 20.0], particle="electron"),),
                materials={1: "water"})
    rm = simulate(mesh, plan, TransportSettings(20_000, 10, 7), progress=False)
    rv = simulate(Image(np.ones(grid.shape), grid), plan, TransportSettings(20_000, 10, 8),
                  labels=Image(np.ones(grid.shape, np.int32), grid), progress=False)
    # box_mesh numbers cubes i fastest with 6 tets each; voxels are flat (k, j, i)
    per_cube = rm.energy_per_batch_mev.reshape(10, n[2], n[1], n[0], 6).sum(axis=4)
    em, ev = per_cube.reshape(10, -1), rv.energy_per_batch_mev
    hit = ev.mean(axis=0) > 0.02 * ev.mean(axis=0).max()
    var = (em[:, hit].var(axis=0, ddof=1) + ev[:, hit].var(axis=0, ddof=1)) / 10
    z = (em[:, hit].mean(axis=0) - ev[:, hit].mean(axis=0)) / np.sqrt(var)
    assert hit.sum() > 20 and np.abs(z).max() < 5.0 and np.mean(z**2) < 2.5


def test_photon_beam_builds_up_dose_below_the_surface():
    """2 MeV parallel beam on water: in the first millimetre the dose is a fraction of the kerma
    (EGSnrc: 27 % at 1 mm, issue 19); beyond the electrons' range (≈ 10 mm) it equals it."""
    shape = (15, 15, 30)
    spacing = np.array([4.0, 4.0, 1.0])
    grid = ImageGrid(spacing / 2 - np.array([30.0, 30.0, 0.0]), spacing, np.eye(3), shape)
    img, lab = Image(np.ones(grid.shape), grid), Image(np.ones(grid.shape, np.int32), grid)
    plan = Plan((PhotonSource("parallel", (0.0, 0.0, -5.0), (0, 0, 1), energies_mev=(2.0,),
                              field_mm=(60.0, 60.0)),), materials={1: "water"})
    depth = {}
    for physics in ("kerma", "dose"):
        r = simulate(img, plan, TransportSettings(400_000, 10, 3, physics=physics), labels=lab,
                     progress=False)
        e = r.energy_per_batch_mev.reshape(10, *grid.shape)[:, :, 5:10, 5:10].sum(axis=(2, 3))
        depth[physics] = e / r.histories_per_batch[:, None]
    k = depth["kerma"].mean(axis=0)
    d, d_err = depth["dose"].mean(axis=0), depth["dose"].std(axis=0, ddof=1) / math.sqrt(10)
    assert d[0] + 4 * d_err[0] < 0.5 * k[0]
    deep = slice(12, 25)
    ratio = d[deep].sum() / k[deep].sum()
    assert abs(ratio - 1.0) < 0.04, ratio
    assert np.all(np.diff(d[:4]) > 0)  # rising through the build-up


def test_dose_mode_on_dask_matches_the_local_run_bitwise():
    distributed = pytest.importorskip("distributed", reason="dask.distributed is not installed "
                                      "(pip install 'tetdose[dask]')")
    from tetdose.transport.run.distributed import simulate_distributed

    mesh = helpers.box_mesh((-20, -20, 0), (20, 20, 40), (3, 3, 4), jitter=0.2, seed=1)
    mesh = mesh.with_data(point_data={"density": 1.0 + 0.01 * mesh.points_mm[:, 2]})
    plan = Plan((PhotonSource("parallel", [0.0, 0.0, -20.0], [0, 0, 1], energies_mev=[3.0],
                              field_mm=[20.0, 20.0]),) + CHARGED[:1])
    settings = TransportSettings(2000, 6, 17, electron_cutoff_mev=0.05)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster, \
            distributed.Client(cluster) as client:
        (remote,) = simulate_distributed(client, [mesh], plan, settings, batches_per_task=4,
                                         progress=False)
    local = simulate(mesh, plan, settings, progress=False)
    assert local.record()["electron_steps"] > 0 and local.energy_per_batch_mev.sum() > 0
    np.testing.assert_array_equal(remote.energy_per_batch_mev, local.energy_per_batch_mev)
    np.testing.assert_array_equal(remote.ledger_per_batch_mev, local.ledger_per_batch_mev)
    np.testing.assert_array_equal(remote.counts_per_batch, local.counts_per_batch)


def test_cli_dose_is_the_default_and_the_record_says_so(tmp_path, capsys):
    from tetdose.cli import main
    from tetdose.core.io import read_image, write_image

    grid = ImageGrid(np.array([-9.0, -9.0, 1.0]), np.full(3, 2.0), np.eye(3), (10, 10, 10))
    write_image(tmp_path / "ct.nrrd", Image(np.zeros(grid.shape, np.int16), grid))
    write_image(tmp_path / "labels.nrrd", Image(np.ones(grid.shape, np.int16), grid))
    (tmp_path / "plan.toml").write_text(textwrap.dedent("""
        [[beam]]
        type = "pencil"
        particle = "electron"
        energy_mev = 4.0
        position_mm = [0.0, 0.0, -5.0]
        [materials]
        1 = "water"
    """))
    common = ["--ct", str(tmp_path / "ct.nrrd"), "--labels", str(tmp_path / "labels.nrrd"),
              "--plan", str(tmp_path / "plan.toml"), "--histories", "2e3"]
    assert main(["dose", *common, "--electron-cutoff-mev", "0.1", "-o",
                 str(tmp_path / "dose.nrrd")]) == 0
    rec = json.loads((tmp_path / "dose.json").read_text())
    # the summary line counts the electrons' energy (a 4 MeV pencil: most of it stays)
    absorbed = float(capsys.readouterr().out.split("absorbed ")[1].split(" MeV")[0])
    led = rec["ledger"]
    assert absorbed == pytest.approx(led["electron_deposited_mev"] + led["electron_cutoff_mev"]
                                     + led["deposited_mev"] + led["cutoff_mev"], rel=1e-3)
    assert absorbed > 2.0
    assert rec["physics"] == "dose" and rec["electron_cutoff_mev"] == 0.1
    assert rec["estimator"] == "analog" and rec["ledger"]["electron_deposited_mev"] > 0
    assert read_image(tmp_path / "dose.nrrd").array.max() > 0
    # kerma mode cannot follow electrons: one line, exit 2, nothing written
    assert main(["dose", *common, "--physics", "kerma", "-o", str(tmp_path / "k.nrrd")]) == 2
    assert not (tmp_path / "k.nrrd").exists()
