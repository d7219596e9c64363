"""`tetdose compare` with σ: physics told from noise, the body stopping at the skin.

A mesh dose and a voxel dose of the same smooth field, each with 2 % Gaussian noise and its σ
(as tetdose writes them: cell_data ``dose_std``, ``dose_std.nrrd`` beside ``dose.nrrd``); the
mesh dose is 4 % high in the half x > 0 only. The CT is water with an air margin of two voxels
inside the mesh's box, so the points in air must drop out of everything.
"""

import json

import numpy as np
import pytest

from tetdose.compare.comparison import compare_doses
from tetdose.compare.consistency import std_image_path
from tetdose.core.body import near_max_gy
from tetdose.core.image import Image
from tetdose.core.io import write_image, write_mesh
from tetdose.core.transfer import mesh_dose_to_grid

from helpers import box_mesh, grid_for

REL = 0.02


def _field(p):
    return 1.0 + 0.3 * np.cos(p[:, 0] / 15.0) * np.cos(p[:, 1] / 20.0)


@pytest.fixture(scope="module")
def case():
    rng = np.random.default_rng(7)
    mesh = box_mesh((-24.0,) * 3, (24.0,) * 3, (16, 16, 16))  # 3 mm cubes, 6 tets each
    grid = grid_for((-24.0,) * 3, (24.0,) * 3, (4.0,) * 3)  # 12³ voxels of 64 mm³
    true_tet = _field(mesh.centroids_mm)
    hot = mesh.centroids_mm[:, 0] > 0
    mesh_dose = true_tet * np.where(hot, 1.04, 1.0) * (1 + REL * rng.standard_normal(mesh.n_tets))
    mesh_std = REL * true_tet * np.where(hot, 1.04, 1.0)
    true_vox = mesh_dose_to_grid(mesh, true_tet, grid).array
    voxel = Image(true_vox * (1 + REL * rng.standard_normal(grid.shape)), grid)
    voxel_std = voxel.with_array(REL * true_vox)
    hu = np.full(grid.shape, -1000, np.int16)
    hu[2:-2, 2:-2, 2:-2] = 0  # water inside, two voxels of air around it
    ct = Image(hu, grid)
    x = grid.voxel_centers_mm()[:, 0].reshape(grid.shape)
    structures = {"hot half": x > 0, "cold half": x < 0}
    return mesh, mesh_dose, mesh_std, voxel, voxel_std, ct, structures


def test_cli_reads_both_sigmas_and_tells_the_systematic_half(case, tmp_path, capsys):
    from tetdose.cli import main

    mesh, mesh_dose, mesh_std, voxel, voxel_std, ct, structures = case
    write_mesh(tmp_path / "dose.vtu", mesh.with_data(cell_data={"dose": mesh_dose,
                                                                "dose_std": mesh_std}))
    write_image(tmp_path / "dose.nrrd", voxel)
    write_image(std_image_path(tmp_path / "dose.nrrd"), voxel_std)
    assert std_image_path(tmp_path / "dose.nrrd").name == "dose_std.nrrd"
    write_image(tmp_path / "ct.nrrd", ct)
    labels = np.where(structures["hot half"], 1, 2).astype(np.int16)
    write_image(tmp_path / "labels.nrrd", Image(labels, voxel.grid))
    assert main(["compare", "-q", "--mesh-dose", str(tmp_path / "dose.vtu"), "--voxel-dose",
                 str(tmp_path / "dose.nrrd"), "--ct", str(tmp_path / "ct.nrrd"),
                 "--structures", str(tmp_path / "labels.nrrd"), "--gamma", "3/3",
                 "--gamma-max-points", "500",
                 "-o", str(tmp_path / "cmp")]) == 0
    out = capsys.readouterr().out
    s = json.loads((tmp_path / "cmp" / "summary.json").read_text())
    # the body stops at the skin: 8³ water voxels, none of the air margin
    assert s["region"]["voxels"] == 8**3 and "body outline" in s["region"]["description"]
    assert "tissue" in s["region"]["description"]
    assert "dose_std" in s["uncertainty"]["mesh"] and "_std" in s["uncertainty"]["voxel"]
    hot, cold = s["structures"]["label 1"], s["structures"]["label 2"]
    for row in (hot, cold):
        assert {"mean_rel_diff", "mean_rel_diff_sigma", "systematic_rel_diff",
                "systematic_fraction"} <= set(row)
    assert hot["systematic_model"] == "all"
    assert hot["systematic_rel_diff"] == pytest.approx(0.04, abs=3 * hot["systematic_rel_diff_sigma"])
    assert hot["mean_rel_diff"] == pytest.approx(0.04, abs=3 * hot["mean_rel_diff_sigma"])
    assert cold["systematic_model"] == "none" and abs(cold["systematic_rel_diff"]) <= 0.01
    assert cold["mean_rel_diff_consistent_with_zero"]
    whole = s["structures"]["compared region"]
    assert whole["systematic_model"] == "part"
    assert whole["systematic_fraction"] == pytest.approx(0.5, abs=0.15)
    g = s["gamma"]["3%/3mm global"]
    assert 0.0 < g["expected_pass_rate_percent"] <= 100.0
    # every DVH point with its σ; the hot half's mean flagged, the cold half's not
    assert s["dvh"]["label 1"]["points"]["Dmean"]["significant"]
    assert not s["dvh"]["label 2"]["points"]["Dmean"]["significant"]
    assert s["dvh"]["label 2"]["points"]["D95"]["mesh_sigma"] > 0
    figures = json.loads((tmp_path / "cmp" / "figures.json").read_text())
    assert any(n.startswith("significance_k") for n in figures)
    assert any(n.startswith("sigma_k") for n in figures)
    assert "label 1: mean difference +4" in out and "statistically consistent" in out
    assert len(s["gamma"]) == 1  # --gamma 3/3 alone


def test_without_sigma_the_doses_are_compared_as_exact_and_the_report_says_so(case):
    mesh, mesh_dose, _, voxel, _, _, _ = case
    s = compare_doses(mesh, mesh_dose, voxel, gamma_max_points=500,
                      criteria=((3.0, 3.0, False),)).summary
    assert "compared as exact" in s["uncertainty"]["mesh"]
    row = s["structures"]["compared region"]
    assert row["mean_rel_diff_sigma"] == 0.0 and row["systematic_rel_diff"] is None


def test_near_max_is_taken_in_tissue_not_in_one_air_voxel():
    dose = np.array([50.0, 2.0, 2.1, 1.9, 1.0])  # the 50 Gy cell is air
    rho = np.array([0.001, 1.0, 1.0, 1.0, 1.0])
    assert near_max_gy(dose, 0.05, rho) == 2.0  # hottest 0.1 cm³ of tissue: 2.1 and 2.0
    assert near_max_gy(dose, 0.05) == 2.1  # without densities: every cell counts
    assert near_max_gy(dose, 1.0, rho) == 2.1  # a cell larger than 0.1 cm³: its own dose
    assert np.isnan(near_max_gy(dose, 0.05, np.zeros(5)))


def test_run_record_reports_the_near_max_in_tissue_not_the_air_voxel():
    """A voxel run whose hottest cell is an air voxel (few interactions in little mass): the
    record's near-maximum is the tissue's; a mesh run's needs its tet volumes."""
    from tetdose.core.image import ImageGrid
    from tetdose.transport.history.result import COUNT_KEYS, DoseResult

    grid = ImageGrid(np.zeros(3), np.full(3, 5.0), np.eye(3), (4, 1, 1))  # 0.125 cm³ voxels
    mass = np.array([1e-4, 0.125, 0.125, 0.125])  # air, then water [g]
    dose_per_mass = np.array([40.0, 2.0, 3.0, 1.0])
    energy = np.tile(dose_per_mass * mass, (2, 1))  # same in both batches

    def result(geometry, g):
        return DoseResult(energy, np.array([5, 5]), mass, np.zeros((2, 5)),
                          np.zeros((2, len(COUNT_KEYS)), np.int64), 1.0, 0, "track_length",
                          geometry, 0.1, "0", grid=g, n_tets=4 if geometry == "mesh" else 0)

    vox = result("voxel", grid)
    ratio = vox.dose_gy[0] / vox.dose_gy[2]  # the air voxel is the maximum, 40/3 of the tissue's
    assert ratio == pytest.approx(40.0 / 3.0)
    rec = vox.record()
    assert rec["near_max_dose_gy"] == pytest.approx(vox.dose_gy[2]) and "D0.1cm³" in rec["near_max"]
    mesh = result("mesh", None)
    assert np.isnan(mesh.near_max_dose_gy())
    assert mesh.near_max_dose_gy(np.full(4, 125.0)) == pytest.approx(mesh.dose_gy[2])


def test_voxel_accumulations_carry_the_phases_sigma():
    """Without motion both voxel accumulations are Σ_p w_p D_p, so their σ is exactly
    sqrt(Σ_p w_p² σ_p²) (phases independent): here 3 phases of weights 0.5, 0.25, 0.25."""
    from tetdose.dose.dose4d import _voxel_way
    from tetdose.motion.phases import PhaseSeries
    from tetdose.transport.history.result import COUNT_KEYS, DoseResult

    grid = grid_for((-8.0,) * 3, (8.0,) * 3, (4.0,) * 3)
    mesh = box_mesh((-4.0,) * 3, (4.0,) * 3, (2, 2, 2))
    w = np.array([0.5, 0.25, 0.25])
    series = PhaseSeries(mesh, np.stack([mesh.points_mm] * 3), time_weight=w)
    rng = np.random.default_rng(3)
    n, mass = grid.n_voxels, np.full(grid.n_voxels, 0.064)
    results = [DoseResult(rng.uniform(0.5, 1.5, (4, n)), np.full(4, 10), mass,
                          np.zeros((4, 5)), np.zeros((4, len(COUNT_KEYS)), np.int64), 1.0, p,
                          "track_length", "voxel", 0.1, "0", grid=grid) for p in range(3)]
    density = [Image(np.ones(grid.shape), grid)] * 3
    v = _voxel_way(series, density, results)
    expected = np.sqrt(sum(wp**2 * r.dose_std_gy**2 for wp, r in zip(w, results, strict=True)))
    assert v.direct_mapping_std.array.ravel() == pytest.approx(expected, rel=1e-9)
    assert v.energy_mass_transfer_std.array.ravel() == pytest.approx(expected, rel=1e-9)
    dose = sum(wp * r.dose_gy for wp, r in zip(w, results, strict=True))
    assert v.energy_mass_transfer.array.ravel() == pytest.approx(dose, rel=1e-9)
    from tetdose.dose.absolute import _scaled_images  # a prescription scales σ with the dose

    scaled = _scaled_images(v, 2.0)
    for name in ("energy_mass_transfer", "energy_mass_transfer_std", "direct_mapping_std"):
        assert getattr(scaled, name).array == pytest.approx(2.0 * getattr(v, name).array)


def test_same_kind_pairs_images_and_meshes(case, tmp_path, capsys):
    """Two voxel runs (σ beside each) and two per-tet runs of one mesh: consistent when
    unbiased, 4 % apart systematically when one is scaled by 1.04."""
    from tetdose.cli import main
    from tetdose.compare.same_kind import compare_meshes

    mesh, mesh_dose, mesh_std, voxel, voxel_std, _, _ = case
    rng = np.random.default_rng(11)
    true = voxel_std.array / REL
    for name, scale in (("a", 1.04), ("b", 1.0)):
        write_image(tmp_path / f"{name}.nrrd", voxel.with_array(
            scale * true * (1 + REL * rng.standard_normal(true.shape))))
        write_image(tmp_path / f"{name}_std.nrrd", voxel_std.with_array(scale * REL * true))
    assert main(["compare", "-q", "--dose", str(tmp_path / "a.nrrd"), "--reference-dose",
                 str(tmp_path / "b.nrrd"), "--gamma-max-points", "300",
                 "-o", str(tmp_path / "cmp")]) == 0
    row = json.loads((tmp_path / "cmp" / "summary.json").read_text())["structures"][
        "compared region"]
    assert row["systematic_model"] == "all"
    assert row["systematic_rel_diff"] == pytest.approx(0.04, abs=3 * row["systematic_rel_diff_sigma"])
    assert "% in 100 % of the points" in capsys.readouterr().out
    cold = mesh.centroids_mm[:, 0] < 0  # the unbiased half of the case's mesh dose
    other = _field(mesh.centroids_mm) * (1 + REL * rng.standard_normal(mesh.n_tets))
    _, s = compare_meshes(mesh, mesh_dose, mesh_std, mesh, other, REL * _field(mesh.centroids_mm))
    whole = s["structures"]["compared region"]
    assert whole["systematic_model"] == "part"
    assert whole["systematic_rel_diff"] == pytest.approx(0.04, abs=3 * whole["systematic_rel_diff_sigma"])
    assert whole["systematic_fraction"] == pytest.approx(1.0 - cold.mean(), abs=0.1)
    with pytest.raises(Exception, match="different tetrahedra"):
        compare_meshes(mesh, mesh_dose, None, box_mesh((0,) * 3, (1,) * 3, (1, 1, 1)),
                       np.ones(6), None)
