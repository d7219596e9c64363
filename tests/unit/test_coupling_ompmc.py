"""ompmc as tetdose's engine (tetdose.coupling.ompmc): units and normalization against NIST μen/ρ,
dose beyond d_max against tetdose's own kerma (an independent code), the build-up it must show,
the mesh energy split, thread independence, and the result working with compare/accumulation.

Skipped where ompmc (the optional extra tetdose[ompmc]) is not installed."""

import sys

import numpy as np
import pytest

from tetdose.core.image import Image, ImageGrid
from tetdose.coupling import ompmc as om
from tetdose.coupling.onto_mesh import result_onto_mesh
from tetdose.dose.accumulate import accumulate_meshes
from tetdose.errors import OptionError, PlanError, TetdoseError
from tetdose.plan.model import Plan
from tetdose.plan.photon_source import PhotonSource
from tetdose.transport import simulate
from tetdose.transport.run.settings import TransportSettings

from helpers import box_mesh, grid_for

pytest.importorskip("ompmc", reason="ompmc (tetdose[ompmc]) is not installed")

#: NIST X-ray mass energy-absorption coefficient of liquid water at 2 MeV [cm²/g]
#: (Hubbell & Seltzer, NIST SRD 126) and its mass attenuation coefficient.
WATER_MU_EN_2MEV = 0.02601
WATER_MU_2MEV = 0.04942


def _water(grid):
    return Image(np.ones(grid.shape), grid), Image(np.ones(grid.shape, dtype=np.int32), grid)


def _parallel(field_mm, energy_mev=2.0, materials=None):
    return Plan((PhotonSource("parallel", [0, 0, -50], [0, 0, 1], energies_mev=[energy_mev],
                              field_mm=field_mm),),
                materials={1: "water"} if materials is None else materials)


def test_thin_slab_kerma_is_fluence_times_energy_times_mu_en():
    """Electrons stopped where they are born (cut-off above the beam energy): the energy a 2 MeV
    parallel beam leaves in a 0.5 mm water slab per photon is E·(μen/ρ)·ρt·(1 − μt/2) (NIST),
    up to μtr/μen ≈ 1.005 and scatter reabsorbed in the slab (< 1 %)."""
    t_mm = 0.5
    grid = ImageGrid([-95.0, -95.0, t_mm / 2], [10.0, 10.0, t_mm], np.eye(3), (20, 20, 1))
    rho, lab = _water(grid)
    r = om.simulate_ompmc(rho, _parallel([100, 100]), TransportSettings(100_000, 10, 1),
                          labels=lab, progress=False,
                          options=om.OmpmcOptions(electron_cutoff_mev=15.0, n_split=50))
    t_cm = t_mm / 10
    expected = 2.0 * WATER_MU_EN_2MEV * t_cm * (1 - WATER_MU_2MEV * t_cm / 2)
    per_batch = r.energy_per_batch_mev.sum(axis=1) / r.histories_per_batch
    assert per_batch.std(ddof=1) / np.sqrt(len(per_batch)) < 0.01 * expected
    assert r.energy_mev.sum() == pytest.approx(expected, rel=0.03)
    # dose per particle in the field: E μen/ρ / A with A = 100 cm² (Gy: MeV/g → J/kg)
    d = r.dose_gy.reshape(grid.shape)[0, 5:15, 5:15].mean()
    assert d == pytest.approx(expected / (t_cm * 100.0) * 1.602176634e-10, rel=0.03)
    assert r.extra["engine"] == "ompmc" and r.extra["media"]["water"]["pegs"] == "H2O521ICRU"
    led = r.ledger
    assert led["source_mev"] == pytest.approx(2.0)
    assert led["deposited_mev"] + led["escaped_mev"] == pytest.approx(2.0, rel=1e-12)


def _central_axis(result, grid, rows=slice(7, 9)):
    """Per-batch dose [Gy] in the central 2 × 2 cm² column, by depth voxel: (B, nz)."""
    e = result.energy_per_batch_mev.reshape(-1, *grid.shape)[:, :, rows, rows].sum(axis=(2, 3))
    m = result.mass_g.reshape(grid.shape)[:, rows, rows].sum(axis=(1, 2))
    return e / result.histories_per_batch[:, None] / m


def _deep_ratio(grid, field_mm, n_histories, seed=1):
    """(dose/kerma per batch in the central column at 30–100 mm, first-voxel dose/kerma): ompmc
    dose against tetdose's own collision kerma (track length) from the same source particles."""
    rho, lab = _water(grid)
    plan = _parallel(field_mm)
    settings = TransportSettings(n_histories, 10, seed)
    dose = om.simulate_ompmc(rho, plan, settings, labels=lab, progress=False)
    kerma = simulate(rho, plan, TransportSettings(n_histories, 10, seed, physics="kerma"),
                     labels=lab, progress=False)
    d, k = _central_axis(dose, grid), _central_axis(kerma, grid)
    deep = slice(6, 20)
    return d[:, deep].sum(axis=1) / k[:, deep].sum(axis=1), d[:, 0].mean() / k[:, 0].mean()


def test_dose_beyond_dmax_is_the_kerma_and_the_surface_is_built_up():
    """2 MeV, 40 × 40 mm² on water: beyond d_max the dose of ompmc (EGSnrc physics) is the
    collision kerma of tetdose's own engine (another code) times β ≈ 1.01 (electrons carry
    energy a few mm downstream), within a few %; in the first 5 mm there is no electron
    equilibrium and the dose is well below the kerma."""
    grid = ImageGrid([-75.0, -75.0, 2.5], [10.0, 10.0, 5.0], np.eye(3), (16, 16, 30))
    per_batch, surface = _deep_ratio(grid, [40, 40], 10_000)
    ratio, sigma = per_batch.mean(), per_batch.std(ddof=1) / np.sqrt(len(per_batch))
    assert sigma < 0.02
    assert ratio == pytest.approx(1.01, abs=0.04)
    assert surface < 0.8


@pytest.mark.slow
def test_dose_beyond_dmax_is_the_kerma_within_two_percent():
    grid = ImageGrid([-95.0, -95.0, 2.5], [10.0, 10.0, 5.0], np.eye(3), (20, 20, 30))
    per_batch, surface = _deep_ratio(grid, [100, 100], 300_000, seed=2)
    ratio, sigma = per_batch.mean(), per_batch.std(ddof=1) / np.sqrt(len(per_batch))
    assert sigma < 0.008
    assert ratio == pytest.approx(1.01, abs=0.02)
    assert surface < 0.8


def test_mesh_dose_keeps_the_voxel_energy_and_threads_do_not_change_it():
    grid = grid_for([-40, -40, 0], [40, 40, 80], [10.0, 10.0, 10.0])
    rho, lab = _water(grid)
    plan = _parallel([60, 60])
    mesh = box_mesh([-20, -20, 10], [20, 20, 50], (2, 2, 2), jitter=0.2, seed=3)
    kerma_like = om.OmpmcOptions(electron_cutoff_mev=15.0, threads=1)
    settings = TransportSettings(4000, 4, 7)
    vox = om.simulate_ompmc(rho, plan, settings, labels=lab, options=kerma_like, progress=False)
    on_mesh = om.simulate_ompmc(rho, plan, settings, labels=lab, mesh=mesh, progress=False,
                                options=om.OmpmcOptions(electron_cutoff_mev=15.0, threads=2))
    # the same histories (Philox streams per history): equal to round-off whatever the thread
    # count (ompmc adds the threads' energies in the order they arrive)
    np.testing.assert_allclose(on_mesh.energy_per_batch_mev,
                               result_onto_mesh(vox, rho, mesh).energy_per_batch_mev, rtol=1e-12)
    inside = vox.energy_per_batch_mev.reshape(-1, *grid.shape)[:, 1:5, 2:6, 2:6].sum(axis=(1, 2, 3))
    np.testing.assert_allclose(on_mesh.energy_per_batch_mev.sum(axis=1), inside, rtol=1e-12)
    assert on_mesh.geometry == "mesh" and on_mesh.extra["engine"] == "ompmc"


def test_target_uncertainty_stops_after_the_batch_that_reaches_it():
    grid = grid_for([-40, -40, 0], [40, 40, 80], [10.0, 10.0, 10.0])
    rho, lab = _water(grid)
    plan = Plan(_parallel([60, 60]).beams, materials={1: "water"}, regions={"phantom": 1})
    opts = om.OmpmcOptions(electron_cutoff_mev=15.0)
    full = om.simulate_ompmc(rho, plan, TransportSettings(20_000, 20, 1), labels=lab,
                             options=opts, progress=False)
    stopped = om.simulate_ompmc(rho, plan, TransportSettings(20_000, 20, 1, target_uncertainty=0.01,
                                                             target_region="phantom"),
                                labels=lab, options=opts, progress=False)
    t = stopped.extra["target"]
    assert t["reached"] and 4 <= t["batches"] < 20 and t["achieved"] <= 0.01
    assert stopped.n_batches == t["batches"]
    np.testing.assert_allclose(stopped.energy_per_batch_mev,
                               full.energy_per_batch_mev[:t["batches"]], rtol=1e-12)


def test_an_arc_reaches_ompmc_as_tetdose_draws_it():
    """A 180° 6 MV arc (photons drawn at their meterset instant): with electrons stopped where
    they are born, ompmc's dose around the isocentre is tetdose's kerma from the same photons."""
    grid = grid_for([-100, -100, -100], [100, 100, 100], [10.0, 10.0, 10.0])
    rho = Image(np.ones(grid.shape), grid)
    plan = Plan.from_dict({"beam": [{
        "type": "linac", "spectrum": "6MV", "isocenter_mm": [0.0, 0.0, 0.0],
        "jaws_mm": [-30.0, 30.0, -30.0, 30.0],
        "arc": {"start_deg": 0.0, "stop_deg": 180.0, "direction": "CW"}}]})
    settings = TransportSettings(20_000, 10, 1)
    dose = om.simulate_ompmc(rho, plan, settings, progress=False,
                             options=om.OmpmcOptions(electron_cutoff_mev=15.0))
    kerma = simulate(rho, plan, TransportSettings(20_000, 10, 1, physics="kerma"), progress=False)
    centre = (slice(8, 12),) * 3
    per_batch = [d.reshape(grid.shape)[centre].sum() for d in dose.energy_per_batch_mev]
    ratio = np.array(per_batch) / kerma.energy_per_batch_mev.reshape(-1, *grid.shape)[
        (slice(None), *centre)].sum(axis=(1, 2, 3))
    assert ratio.std(ddof=1) / np.sqrt(len(ratio)) < 0.01
    assert ratio.mean() == pytest.approx(1.0, abs=0.02)


def test_results_work_with_accumulation_and_images():
    grid = grid_for([-30, -30, 0], [30, 30, 60], [10.0, 10.0, 10.0])
    rho, lab = _water(grid)
    plan = _parallel([40, 40])
    mesh = box_mesh([-20, -20, 10], [20, 20, 40], (2, 2, 1)).with_data(
        point_data={"density": np.ones(18)})
    opts = om.OmpmcOptions(electron_cutoff_mev=15.0)
    phases = [om.simulate_ompmc(rho, plan, TransportSettings(2000, 4, 1, stream=k), labels=lab,
                                mesh=mesh, options=opts, progress=False) for k in range(2)]
    acc = accumulate_meshes([mesh, mesh], [p.dose_gy for p in phases],
                            dose_std_gy=[p.dose_std_gy for p in phases])
    np.testing.assert_allclose(acc.dose_gy, (phases[0].dose_gy + phases[1].dose_gy) / 2,
                               rtol=1e-12)
    assert np.all(acc.dose_std_gy > 0)
    out = phases[0].to_mesh(mesh)
    assert np.array_equal(out.cell_data["dose"], phases[0].dose_gy)
    dose_img, std_img = om.simulate_ompmc(rho, plan, TransportSettings(2000, 4, 1), labels=lab,
                                          options=opts, progress=False).to_images()
    assert dose_img.grid.same_as(grid) and dose_img.array.max() > 0 and std_img.array.max() > 0


def test_phase_space_of_the_run_reads_back_with_a_reader_written_from_the_format(tmp_path):
    """IAEA INDC(NDS)-0484 record: int8 type (sign = sign of w), float32 E (negative: new
    history), x, y, z [cm], u, v, weight; little endian."""
    from tetdose.coupling.iaea_phsp import read_phase_space, write_phase_space

    rng = np.random.default_rng(1)
    d = rng.normal(size=(50, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    e, pos, w = rng.uniform(0.1, 6, 50), rng.uniform(-50, 50, (50, 3)), rng.uniform(0, 2, 50)
    head, data = write_phase_space(tmp_path / "beam", e, pos, d, w)
    text = head.read_text()
    assert "$RECORD_LENGTH:\n29" in text and "$PARTICLES:\n50" in text
    raw = np.frombuffer(data.read_bytes(), dtype=np.dtype(
        [("t", "i1"), ("e", "<f4"), ("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("u", "<f4"),
         ("v", "<f4"), ("wt", "<f4")]))
    assert np.all(np.abs(raw["t"]) == 1) and np.all(np.sign(raw["t"]) == np.where(d[:, 2] < 0,
                                                                                   -1, 1))
    np.testing.assert_allclose(-raw["e"], e, rtol=1e-7)
    np.testing.assert_allclose(np.stack([raw["x"], raw["y"], raw["z"]], 1), pos, rtol=1e-7)
    back = read_phase_space(tmp_path / "beam.IAEAheader")
    np.testing.assert_allclose(back.direction, d, atol=1e-6)
    np.testing.assert_allclose(back.weight, w, rtol=1e-7)
    assert back.new_history.all()


def test_source_particles_are_those_tetdose_transports():
    """A point source half aimed off the grid: the particles that miss it (a slab test on the
    drawn rays) are exactly the ones tetdose's own run counts as missing the world."""
    from tetdose.transport.sources.particles import source_particles

    grid = grid_for([0, 0, 0], [40, 40, 40], [10.0, 10.0, 10.0])
    plan = Plan((PhotonSource("point", [60.0, 45, 20], [-1, 0, 0], energies_mev=[0.5, 1.5],
                              line_weights=[1, 3], half_angle_deg=40.0),))
    settings = TransportSettings(3000, 3, 5, stream=2)
    p = source_particles(plan, settings, 0, 3000)
    lo, hi = grid.bounds_grid_frame()
    hits = om.ray_hits_box(grid.to_grid_frame(p.position_mm), p.direction @ grid.direction, lo, hi)
    run = simulate(Image(np.ones(grid.shape), grid), plan,
                   TransportSettings(3000, 3, 5, stream=2, physics="kerma"), progress=False)
    assert 0 < hits.sum() < 3000
    assert run.counts_per_batch[:, 6].sum() == 3000 - hits.sum()
    assert np.mean(p.energy_mev == 1.5) == pytest.approx(0.75, abs=0.03)


def test_bad_input_is_refused_with_the_fix():
    grid = grid_for([0, 0, 0], [40, 40, 40], [10.0, 10.0, 10.0])
    rho, _ = _water(grid)
    away = Plan((PhotonSource("parallel", [0, 0, -50], [0, 0, -1], energies_mev=[1.0],
                              field_mm=[10, 10]),))
    with pytest.raises(PlanError, match="miss"):
        om.simulate_ompmc(rho, away, TransportSettings(100, 2), progress=False)
    plan = _parallel([10, 10], materials={})
    with pytest.raises(OptionError, match="AE"):
        om.simulate_ompmc(rho, plan, TransportSettings(100, 2), progress=False,
                          options=om.OmpmcOptions(pegs="700icru", electron_cutoff_mev=0.05))
    with pytest.raises(PlanError, match="not in 521icru"):
        om.simulate_ompmc(rho, plan, TransportSettings(100, 2), progress=False,
                          options=om.OmpmcOptions(media={"soft_tissue": "ADIPOSE"}))
    with pytest.raises(OptionError):
        om.OmpmcOptions(n_split=0)


def test_missing_ompmc_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "ompmc", None)  # import ompmc → ImportError
    with pytest.raises(TetdoseError, match=r"tetdose\[ompmc\]"):
        om.ompmc_module()


def test_electron_beams_reach_ompmc_as_electrons():
    """The phase space carries the plan's particle (IAEA 2 for electrons): a 6 MeV electron
    beam deposits most of its energy in 40 mm of water (a photon beam would pass through)."""
    e_beam = PhotonSource("parallel", [0, 0, -50], [0, 0, 1], energies_mev=[6.0],
                          field_mm=[10, 10], particle="electron")
    assert om.iaea_particle(Plan((e_beam,))) == 2
    with pytest.raises(PlanError, match="one particle"):
        om.iaea_particle(Plan((e_beam, PhotonSource("parallel", [0, 0, -50], [0, 0, 1],
                                                    energies_mev=[6.0], field_mm=[10, 10]))))
    grid = grid_for([-30, -30, 0], [30, 30, 40], [10.0, 10.0, 2.0])
    rho, lab = _water(grid)
    r = om.simulate_ompmc(rho, Plan((e_beam,), materials={1: "water"}),
                          TransportSettings(200, 2, 1, electron_cutoff_mev=0.2), labels=lab,
                          progress=False, options=om.OmpmcOptions(electron_cutoff_mev=0.2,
                                                                  n_split=1))
    assert r.ledger["deposited_mev"] > 0.8 * 6.0


def test_ompmc_scores_nothing_below_its_density_threshold():
    """2 MeV photons through water with 2 mm layers of low density: ompmc leaves the layers below
    UNSCORED_BELOW_G_CM3 at zero (warning, recorded); tetdose's engine gives every layer the dose
    of the water in front times about the stopping-power ratio (Bragg–Gray cavities: the electron
    fluence crosses a thin layer unchanged; air/water ≈ 0.88, lung/water ≈ 1)."""
    dens = (0.02, 0.04, 0.05, 0.1)
    grid = ImageGrid([0.0, 0.0, 0.5], [200.0, 200.0, 1.0], np.eye(3), (1, 1, 40))
    rho = np.ones(grid.shape)
    for i, d in enumerate(dens):
        rho[20 + 2 * i:22 + 2 * i] = d
    density = Image(rho, grid)
    plan = Plan((PhotonSource("pencil", (0.0, 0.0, -5.0), (0, 0, 1), energies_mev=(2.0,)),))
    settings = TransportSettings(20_000, 4, 1, electron_cutoff_mev=0.189)
    with pytest.warns(UserWarning, match="ompmc scores no energy"):
        res = om.simulate_ompmc(density, plan, settings, progress=False, options=om.OmpmcOptions(
            pegs="700icru", electron_cutoff_mev=0.189, threads=1))
    assert res.extra["unscored_voxels"] == 4
    ours = simulate(density, plan, settings, progress=False)
    per_mass = {}
    for name, r in (("ompmc", res), ("tetdose", ours)):
        d = r.energy_per_batch_mev.sum(axis=0) / r.mass_g.reshape(-1)
        per_mass[name] = np.array([d[20 + 2 * i:22 + 2 * i].mean() for i in range(len(dens))])
        per_mass[name] /= d[12:20].mean()  # the water in front
    assert np.all(per_mass["ompmc"][:2] == 0.0) and np.all(per_mass["ompmc"][2:] > 0.8)
    assert np.all((per_mass["tetdose"] > 0.78) & (per_mass["tetdose"] < 1.08)), per_mass
