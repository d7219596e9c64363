"""Dose-mode variance reduction is unbiased: photon splitting with electron Russian roulette,
photon splitting that follows the electrons (XVMC's scheme), XVMC's splitting along the ray with
electron history repetition, and range rejection give the analog
dose within statistics on a water / lung / bone slab, the ledger (with its roulette column)
closes in every batch, one or two threads give the same bits; the pilot run that estimates a
run's time runs coupled histories, so the estimate counts the electrons."""

from __future__ import annotations

import warnings
from dataclasses import replace
from functools import lru_cache
from pathlib import Path

import numpy as np
import pytest

from tetdose.core.image import Image, ImageGrid
from tetdose.errors import PlanError
from tetdose.transport import PhotonSource, Plan, TransportSettings, World, simulate
from tetdose.transport.run import job as job_module
from tetdose.transport.run.job import build_job, cross_sections, preflight

from helpers import same_bits_with_one_or_two_threads

#: Slab along z [mm]: water 0–20, lung (0.26) 20–40, cortical bone (1.85) 40–50, water 50–80.
LAYERS = ((0, 20, 1.0, 1), (20, 40, 0.26, 2), (40, 50, 1.85, 3), (50, 80, 1.0, 1))
SLAB_PLAN = Plan((PhotonSource("parallel", (0.0, 0.0, -5.0), (0, 0, 1), energies_mev=(2.0,),
                               field_mm=(40.0, 40.0)),),
                 materials={1: "water", 2: "lung", 3: "cortical_bone"})


def slab_phantom() -> tuple[Image, Image]:
    """12 × 12 × 40 voxels of 5 × 5 × 2 mm³: (density [g/cm³], labels)."""
    spacing = np.array([5.0, 5.0, 2.0])
    grid = ImageGrid(spacing / 2 - np.array([30.0, 30.0, 0.0]), spacing, np.eye(3), (12, 12, 40))
    rho = np.empty(grid.shape)
    lab = np.empty(grid.shape, np.int32)
    for lo, hi, density, label in LAYERS:
        rho[lo // 2:hi // 2], lab[lo // 2:hi // 2] = density, label
    return Image(rho, grid), Image(lab, grid)


def _layer_dose(r, grid: ImageGrid) -> tuple[np.ndarray, np.ndarray]:  # noqa: ANN001
    """(mean, σ) of the energy per history per slab layer [MeV] in the central 20 × 20 mm²."""
    e = r.energy_per_batch_mev.reshape(-1, *grid.shape)[:, :, 4:8, 4:8].sum(axis=(2, 3))
    per = np.stack([e[:, lo // 2:hi // 2].sum(axis=1) for lo, hi, _, _ in LAYERS], axis=1)
    per /= r.histories_per_batch[:, None]
    return per.mean(axis=0), per.std(axis=0, ddof=1) / np.sqrt(len(per))


def _closes(r) -> None:  # noqa: ANN001
    led = r.ledger_per_batch_mev
    assert np.allclose(led[:, 1:].sum(axis=1), led[:, 0], rtol=1e-9, atol=0.0)
    local = led[:, [1, 3, 5, 7]].sum(axis=1)
    np.testing.assert_allclose(r.energy_per_batch_mev.sum(axis=1), local, rtol=1e-9)


@lru_cache(maxsize=1)
def _analog_slab() -> tuple[np.ndarray, np.ndarray, float]:
    """(layer mean, σ, electron tracks per history) of the analog run on the slab."""
    rho, lab = slab_phantom()
    r = simulate(rho, SLAB_PLAN, TransportSettings(60_000, 10, 5, electron_cutoff_mev=0.1),
                 labels=lab, progress=False)
    _closes(r)
    m, s = _layer_dose(r, rho.grid)
    assert np.all(s < 0.05 * m)  # the comparisons have teeth: each layer to a few %
    return m, s, r.record()["electron_tracks"] / 60_000


@pytest.mark.parametrize(("scheme", "n", "extra"), [
    ("roulette", 30_000, {}), ("follow", 12_000, {}), ("repeat", 12_000, {}),
    ("repeat", 12_000, {"quasi_random": True}),
    ("repeat", 8_000, {"photon_splitting": 8, "secondary_photon_splitting": 2})])
def test_photon_splitting_gives_the_analog_dose_on_a_water_lung_bone_slab(scheme, n, extra):
    """Splitting 4 with Russian roulette for the electrons (EGSnrc), following them with weight
    1/4 and rouletting the secondary photons (XVMC), or that with one electron track, sampled in
    the first copy's medium, replayed for the four copies and scaled to lung and bone (XVMC's
    history repetition), also with the source photons from scrambled Sobol points, or with the
    source photon in 8 copies and every later photon in 2: the layer doses agree with the
    analog run within 3σ, the ledger closes in every batch with a roulette column near 0;
    following or replaying sets about four times as many electron tracks in motion per source
    photon."""
    rho, lab = slab_phantom()
    st = TransportSettings(n, 10, 6, electron_cutoff_mev=0.1,
                           **{"photon_splitting": 4, "splitting_scheme": scheme, **extra})
    r = simulate(rho, SLAB_PLAN, st, labels=lab, progress=False)
    _closes(r)
    assert r.lost_photons == 0
    assert r.ledger["roulette_mev"] != 0.0  # the roulette ran
    assert abs(r.ledger["roulette_mev"]) < 0.02 * r.ledger["source_mev"]
    rec = r.record()
    assert rec["photon_splitting"] == st.photon_splitting and rec["splitting_scheme"] == scheme
    assert rec.get("secondary_photon_splitting") == extra.get("secondary_photon_splitting")
    m1, s1, tracks1 = _analog_slab()
    m4, s4 = _layer_dose(r, rho.grid)
    z = (m4 - m1) / np.hypot(s1, s4)
    assert np.all(np.abs(z) < 3.0), z
    tracks = r.record()["electron_tracks"] / n
    if scheme != "roulette":
        assert tracks > 3.0 * tracks1, (tracks, tracks1)
    else:
        assert tracks < 1.5 * tracks1, (tracks, tracks1)


def test_splitting_along_the_ray_divides_the_variance_per_source_photon():
    """XVMC's splitting along the ray (repeat, N = 8): the copies interact at stratified depths
    and every photon of weight 1 is split again, so the variance per source photon of every
    layer's energy falls several-fold (N/σ²-ratio ≈ 1.2–1.6 measured; > 2.5 asserted against 8
    for the 10-batch σ's own scatter); the layers agree with the analog run, no stack
    overflows."""
    rho, lab = slab_phantom()
    n = 8000
    r = simulate(rho, SLAB_PLAN, TransportSettings(n, 10, 12, electron_cutoff_mev=0.1,
                                                   photon_splitting=8, splitting_scheme="repeat"),
                 labels=lab, progress=False)
    _closes(r)
    assert r.record()["stack_overflows"] == 0
    m1, s1, _ = _analog_slab()
    m8, s8 = _layer_dose(r, rho.grid)
    assert np.all(np.abs(m8 - m1) < 3.0 * np.hypot(s1, s8))
    ratio = (s1**2 * 60_000) / (s8**2 * n)
    assert np.all(ratio > 2.5), ratio


def test_range_rejection_gives_the_analog_dose_on_a_water_lung_bone_slab():
    """Electrons up to 2 MeV that cannot leave their voxel deposit there at once: the layer
    doses agree with the analog run within 3σ, with fewer electron steps (in 10 mm voxels, where
    it has room to act), and the ledger closes."""
    rho, lab = slab_phantom()
    runs, steps = {}, {}
    for rr in (0.0, 2.0):
        r = simulate(rho, SLAB_PLAN, TransportSettings(60_000, 10, 5, electron_cutoff_mev=0.1,
                                                       range_rejection_mev=rr),
                     labels=lab, progress=False)
        _closes(r)
        runs[rr] = _layer_dose(r, rho.grid)
        steps[rr] = r.record()["electron_steps"]
        assert r.record()["range_rejection_mev"] == rr
    (m0, s0), (m2, s2) = runs[0.0], runs[2.0]
    z = (m2 - m0) / np.hypot(s0, s2)
    assert np.all(np.abs(z) < 3.0), z
    assert steps[2.0] < steps[0.0]


def test_range_rejection_gives_the_analog_dose_in_linear_density_tets():
    """Tets of linear density (a gradient along x, a jump 1.0 → 0.3 g/cm³ smeared across the
    tets at z = 30 mm; water / lung / lung regions): energy per region and per 10 mm tet layer
    with range rejection agrees with the analog run within 3σ, with fewer electron steps."""
    from test_transport import _slab_mesh_with_regions

    mesh = _slab_mesh_with_regions()
    plan = Plan((PhotonSource("parallel", (0.0, 0.0, -5.0), (0, 0, 1), energies_mev=(2.0,),
                              field_mm=(30.0, 30.0)),), materials={1: "water", 2: "lung", 3: "lung"})
    layer = np.minimum((mesh.centroids_mm[:, 2] // 10).astype(int), 5)
    runs, steps = {}, {}
    for rr in (0.0, 2.0):
        r = simulate(mesh, plan, TransportSettings(40_000, 10, 5, electron_cutoff_mev=0.05,
                                                   range_rejection_mev=rr), progress=False)
        _closes(r)
        e = r.energy_per_batch_mev / r.histories_per_batch[:, None]
        per = np.stack([e[:, layer == i].sum(axis=1) for i in range(6)], axis=1)
        runs[rr] = per.mean(axis=0), per.std(axis=0, ddof=1) / np.sqrt(len(per))
        steps[rr] = r.record()["electron_steps"]
    (m0, s0), (m2, s2) = runs[0.0], runs[2.0]
    z = (m2 - m0) / np.hypot(s0, s2)
    assert np.all(np.abs(z) < 3.0), z
    assert steps[2.0] < 0.95 * steps[0.0], steps


def test_history_repetition_gives_the_analog_dose_in_linear_density_tets():
    """The replayed electron tracks walk linear-density tets (mass thicknesses) and are scaled
    from water to lung: energy per 10 mm tet layer with splitting 4 and one replayed track per
    source photon agrees with the analog run within 3σ, and the ledger closes."""
    from test_transport import _slab_mesh_with_regions

    mesh = _slab_mesh_with_regions()
    plan = Plan((PhotonSource("parallel", (0.0, 0.0, -5.0), (0, 0, 1), energies_mev=(2.0,),
                              field_mm=(30.0, 30.0)),), materials={1: "water", 2: "lung", 3: "lung"})
    layer = np.minimum((mesh.centroids_mm[:, 2] // 10).astype(int), 5)
    runs = {}
    for scheme, split, n in (("roulette", 1, 30_000), ("repeat", 4, 10_000)):
        r = simulate(mesh, plan, TransportSettings(n, 10, 7, electron_cutoff_mev=0.1,
                                                   photon_splitting=split,
                                                   splitting_scheme=scheme), progress=False)
        _closes(r)
        e = r.energy_per_batch_mev / r.histories_per_batch[:, None]
        per = np.stack([e[:, layer == i].sum(axis=1) for i in range(6)], axis=1)
        runs[scheme] = per.mean(axis=0), per.std(axis=0, ddof=1) / np.sqrt(len(per))
    (m0, s0), (m4, s4) = runs["roulette"], runs["repeat"]
    z = (m4 - m0) / np.hypot(s0, s4)
    assert np.all(np.abs(z) < 3.0), z
    assert np.all(s0 < 0.05 * m0)


def test_splitting_one_is_the_analog_run_bit_for_bit():
    """photon_splitting=1 draws no roulette number and weights nothing, with any scheme: the
    earlier kernel."""
    rho, lab = slab_phantom()
    a, b, c, d = (simulate(rho, SLAB_PLAN, TransportSettings(2000, 2, 3, **kw), labels=lab,
                           progress=False)
                  for kw in ({}, {"photon_splitting": 1},
                             {"photon_splitting": 1, "splitting_scheme": "follow"},
                             {"photon_splitting": 1, "splitting_scheme": "repeat"}))
    np.testing.assert_array_equal(a.energy_per_batch_mev, b.energy_per_batch_mev)
    np.testing.assert_array_equal(a.energy_per_batch_mev, c.energy_per_batch_mev)
    np.testing.assert_array_equal(a.energy_per_batch_mev, d.energy_per_batch_mev)
    assert a.ledger["roulette_mev"] == 0.0


def test_photon_splitting_setting_is_checked():
    with pytest.raises(PlanError, match="photon_splitting"):
        TransportSettings(100, 2, photon_splitting=0)
    with pytest.raises(PlanError, match="splitting_scheme"):
        TransportSettings(100, 2, splitting_scheme="xvmc")
    with pytest.raises(PlanError, match="secondary_photon_splitting"):
        TransportSettings(100, 2, photon_splitting=8, secondary_photon_splitting=16,
                          splitting_scheme="repeat")
    with pytest.raises(PlanError, match="needs splitting_scheme='repeat'"):
        TransportSettings(100, 2, photon_splitting=8, secondary_photon_splitting=4)
    st = TransportSettings(100, 2, photon_splitting=8, splitting_scheme="repeat")
    assert st.secondary_copies == 8
    assert replace(st, secondary_photon_splitting=2).secondary_copies == 2


def test_split_dose_same_bits_with_one_or_two_threads(tmp_path):
    same_bits_with_one_or_two_threads(tmp_path, Path(__file__).parent, """
        from test_dose_variance_reduction import SLAB_PLAN, slab_phantom
        from tetdose.transport import TransportSettings, simulate
        rho, lab = slab_phantom()
        r = simulate(rho, SLAB_PLAN, TransportSettings(3000, 8, 9, electron_cutoff_mev=0.1,
                                                       photon_splitting=3),
                     labels=lab, progress=False)
    """)


def test_preflight_times_coupled_histories_so_the_estimate_counts_the_electrons(monkeypatch):
    """The pilot runs the run's own physics: a dose-mode estimate is several times the kerma
    one (electron steps cost more than the photon flights), and the long-run warning quotes it."""
    monkeypatch.setattr(job_module, "PILOT_HISTORIES", 20_000)  # kerma's pilot above the noise
    rho, lab = slab_phantom()
    world = World(density=rho, labels=lab)
    est = {}
    for physics, cut in (("kerma", 0.2), ("dose", 0.01)):
        st = TransportSettings(1_000_000, 10, 1, physics=physics, electron_cutoff_mev=cut,
                               range_rejection_mev=0.0)
        job, _ = build_job(world, SLAB_PLAN, st)
        xs = cross_sections(job, st)
        preflight(job, xs, st, 1)  # warm (compile, tables)
        est[physics] = min(preflight(job, xs, st, 1) for _ in range(2))
    assert est["dose"] > 4.0 * est["kerma"], est  # ≈ 20× on a quiet machine
    monkeypatch.setattr(job_module, "LONG_RUN_S", 0.5 * est["dose"])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        preflight(job, xs, st, 1)
    assert any("histories will take about" in str(w.message) for w in caught)


@pytest.mark.slow
def test_variance_reduction_is_unbiased_on_the_demo_phase_0():
    """The demo's phantom at phase 0 (its CT through the Schneider calibration, its labels and
    materials) under the demo's 6 MV fields: the mean dose in the tumour, lung, bone, heart and body
    with range rejection, with photon splitting, and with XVMC's splitting along the ray (its
    replayed tracks scaled across the thorax's media; also as the demo runs it, the source photon
    in 64 copies, later photons in 32, quasi-random source photons), agree with the analog run
    within 3σ."""
    from tetdose.core.calibration import HUCalibration
    from tetdose.phantoms import make_phantom
    from tetdose.study import StudyConfig, _plan

    config = StudyConfig.quick()
    ph = make_phantom(config.phantom, seed=config.seed, size=config.size)
    label_of = {name: label for label, name in ph.label_names.items()}
    rho = Image(HUCalibration.schneider2000()(ph.ct.array), ph.ct.grid)
    tumour = ph.mesh.centroids_mm[ph.mesh.region == label_of["tumour"]].mean(axis=0)
    plan = _plan(tumour, config, label_of["tumour"])
    plan = Plan(treatment_beams=plan.treatment_beams, materials=ph.materials)
    lab = ph.labels.array.ravel()
    masks = {name: lab == label_of[name] for name in ("tumour", "lung", "bone", "heart")}
    masks["body"] = rho.array.ravel() > 0.5
    means = {}
    for name, kw in (("analog", {"range_rejection_mev": 0.0}),
                     ("range rejection", {"range_rejection_mev": 2.0}),
                     ("splitting 4", {"range_rejection_mev": 0.0, "photon_splitting": 4}),
                     ("along the ray 16", {"photon_splitting": 16,
                                           "splitting_scheme": "repeat"}),
                     ("along the ray 64 / 32, quasi-random", {
                         "photon_splitting": 64, "secondary_photon_splitting": 32,
                         "splitting_scheme": "repeat", "quasi_random": True})):
        r = simulate(rho, plan, TransportSettings(200_000, 20, 11, **kw), labels=ph.labels,
                     progress=False)
        _closes(r)
        per = np.stack([r.energy_per_batch_mev[:, m].sum(axis=1) / r.mass_g[m].sum()
                        for m in masks.values()], axis=1) / r.histories_per_batch[:, None]
        means[name] = (per.mean(axis=0), per.std(axis=0, ddof=1) / np.sqrt(len(per)))
    m0, s0 = means["analog"]
    for name in list(means)[1:]:
        m, s = means[name]
        z = (m - m0) / np.hypot(s, s0)
        assert np.all(np.abs(z) < 3.0), (name, dict(zip(masks, z, strict=True)))
        assert np.all(s0 < 0.05 * m0)  # each mean to a few %: the comparison has teeth
