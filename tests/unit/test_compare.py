"""Dose comparison: energy-conserving resampling, point location, gamma, DVH, profiles, CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.special import erf

from tetdose.compare.dvh import dvh, image_dvh, mesh_dvh
from tetdose.compare.gamma import gamma_index
from tetdose.compare.profiles import image_profile, mesh_profile
from tetdose.core.image import Image, ImageGrid
from tetdose.core.mass import tet_mass_g
from tetdose.core.mesh import TetMesh
from tetdose.core.transfer import (
    grid_dose_to_mesh,
    locate_points,
    mesh_dose_to_grid,
    mesh_mass_on_grid,
)
from tetdose.phantoms import mesh_labels


def box_mesh(size=(12, 10, 8), box=(slice(2, 6), slice(2, 8), slice(2, 10)), spacing=4.0,
             edge_mm=8.0) -> TetMesh:
    """A block of tetrahedra meshed from a box label on a small grid."""
    grid = ImageGrid((0, 0, 0), (spacing,) * 3, np.eye(3), size)
    lab = np.zeros(grid.shape, np.int32)
    lab[box] = 1
    return mesh_labels(Image(lab, grid), target_edge_mm=edge_mm)


def rotated_grid() -> ImageGrid:
    c, s = np.cos(0.3), np.sin(0.3)
    rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    return ImageGrid((-5, -20, -3), (3, 2.5, 3.5), rot, (30, 30, 20))


@pytest.fixture(scope="module")
def mesh_and_fields():
    mesh = box_mesh()
    rng = np.random.default_rng(1)
    return mesh, rng.uniform(0.2, 1.8, mesh.n_points), rng.uniform(0.0, 2.0, mesh.n_tets)


def brute_force_locate(mesh: TetMesh, x: np.ndarray) -> np.ndarray:
    p = mesh.points_mm[mesh.tets]
    a = np.stack([p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]], axis=2)
    lam = np.linalg.solve(a, (x - p[:, 0])[:, :, None])[..., 0]
    return np.flatnonzero(np.column_stack([1 - lam.sum(1), lam]).min(axis=1) >= -1e-9)


# --- resampling --------------------------------------------------------------------------------

def test_mesh_voxel_mesh_round_trip_conserves_energy(mesh_and_fields):
    mesh, rho, dose = mesh_and_fields
    grid = rotated_grid()  # covers the mesh, oblique to it
    mass_k = tet_mass_g(mesh, rho)
    img = mesh_dose_to_grid(mesh, dose, grid, density_g_cm3=rho)
    mass_j = mesh_mass_on_grid(mesh, grid, density_g_cm3=rho).array
    back = grid_dose_to_mesh(mesh, img, density_g_cm3=rho)
    e0 = float(np.dot(dose, mass_k))
    assert np.isclose(mass_j.sum(), mass_k.sum(), rtol=1e-12)
    assert abs(float((img.array * mass_j).sum()) - e0) <= 1e-9 * e0
    assert abs(float(np.dot(back, mass_k)) - e0) <= 1e-9 * e0
    assert not np.allclose(back, dose)  # the round trip smooths: energy, not identity


def test_constant_dose_stays_constant(mesh_and_fields):
    mesh, rho, _ = mesh_and_fields
    grid = rotated_grid()
    img = mesh_dose_to_grid(mesh, np.full(mesh.n_tets, 1.7), grid, density_g_cm3=rho)
    covered = mesh_mass_on_grid(mesh, grid, density_g_cm3=rho).array > 0
    assert np.allclose(img.array[covered], 1.7, rtol=1e-12)
    assert np.all(img.array[~covered] == 0)
    assert np.allclose(grid_dose_to_mesh(mesh, img, density_g_cm3=rho), 1.7, rtol=1e-12)


def test_mass_weighting_differs_from_volume_weighting():
    mesh = box_mesh()
    x = mesh.points_mm[:, 0]
    rho = 0.5 + (x - x.min()) / np.ptp(x)  # density rises along x
    dose = mesh.centroids_mm[:, 0].copy()
    grid = ImageGrid((0, 0, 0), (40.0, 40.0, 40.0), np.eye(3), (2, 2, 2))  # coarse: mixes tets
    by_mass = mesh_dose_to_grid(mesh, dose, grid, density_g_cm3=rho).array
    by_volume = mesh_dose_to_grid(mesh, dose, grid, density_g_cm3=np.ones(mesh.n_points)).array
    hit = by_volume > 0
    assert np.all(by_mass[hit] > by_volume[hit])  # heavier tets (larger x) get more weight


def test_locate_points_matches_brute_force(mesh_and_fields):
    mesh = mesh_and_fields[0]
    rng = np.random.default_rng(2)
    lo, hi = mesh.bounds_mm()
    pts = rng.uniform(lo - 3, hi + 3, (400, 3))
    tet, bary = locate_points(mesh, pts)
    for q in range(len(pts)):
        expected = brute_force_locate(mesh, pts[q])
        if len(expected) == 0:
            assert tet[q] == -1
        else:
            assert tet[q] in expected
            corners = mesh.points_mm[mesh.tets[tet[q]]]
            assert np.allclose(bary[q] @ corners, pts[q], atol=1e-9)
    assert 50 < (tet >= 0).sum() < 400


# --- gamma -------------------------------------------------------------------------------------

def line_images(ref_1d, ev_1d, spacing=1.0):
    grid = ImageGrid((0, 0, 0), (spacing, 1.0, 1.0), np.eye(3), (len(ref_1d), 3, 3))
    as_img = lambda v: Image(np.broadcast_to(v, (3, 3, len(v))).copy(), grid)  # noqa: E731
    return as_img(ref_1d), as_img(ev_1d)


def brute_force_gamma_1d(x, ref, ev_fn, dd, dta, max_gamma=2.0):
    """min over a fine 1-D search of the evaluated function (the shift is along x only)."""
    s = np.linspace(-max_gamma * dta, max_gamma * dta, 4001)
    cand = s[None, :] ** 2 / dta**2 + (ev_fn(x[:, None] + s[None, :]) - ref[:, None]) ** 2 / dd**2
    return np.sqrt(cand.min(axis=1))


def test_gamma_of_a_dose_with_itself_is_zero():
    rng = np.random.default_rng(3)
    grid = ImageGrid((0, 0, 0), (2.0, 2.0, 3.0), np.eye(3), (14, 12, 10))
    dose = Image(rng.uniform(0, 2, grid.shape), grid)
    res = gamma_index(dose, dose, local=True)
    assert res.pass_rate_percent == 100.0
    assert np.nanmax(res.gamma) == 0.0
    assert res.n_evaluated == int((dose.array >= 0.1 * dose.array.max()).sum())


def test_gamma_of_shifted_error_function_matches_analytic_pattern():
    x = np.arange(80.0)

    def profile(v):
        return 1.0 + 0.8 * erf((v - 40.0) / 4.0)

    # evaluated dose = reference shifted by +2 mm; its interpolant is piecewise linear
    ev_1d = profile(x - 2.0)
    ref_img, ev_img = line_images(profile(x), ev_1d)
    wide = gamma_index(ref_img, ev_img, dose_percent=3, dta_mm=3, threshold_percent=0)
    assert wide.pass_rate_percent == 100.0  # a 2 mm shift passes 3 mm DTA everywhere
    tight = gamma_index(ref_img, ev_img, dose_percent=1, dta_mm=1, threshold_percent=0)
    g = tight.gamma[1, 1]
    steep = np.abs(np.gradient(profile(x))) > 0.1  # Gy/mm, vs 1 % of 1.8 Gy per mm
    assert np.all(g[steep] > 1) and np.all(g[np.abs(x - 40) > 20] < 1)
    # sub-voxel search: against a fine brute-force minimisation of the same interpolant
    interp = lambda v: np.interp(v, x, ev_1d, left=np.nan, right=np.nan)  # noqa: E731
    expected = brute_force_gamma_1d(x, profile(x), interp, 0.01 * 1.8, 1.0)
    inner = slice(3, -3)
    finite = np.isfinite(g[inner])
    assert np.allclose(g[inner][finite], expected[inner][finite], atol=0.03)
    assert np.all(expected[inner][~finite] >= 2.0 - 0.03)


def test_local_and_global_gamma_differ_as_they_should():
    ref_1d = np.where(np.arange(60) < 30, 1.0, 0.3)
    ref_img, ev_img = line_images(ref_1d, 1.02 * ref_1d)
    deep = np.r_[0:20, 40:60]  # ≥ 10 voxels from the step: beyond the 3 mm search radius
    kw = {"dose_percent": 1, "dta_mm": 1, "threshold_percent": 0, "max_gamma": 3.0,
          "interp_fraction": 2}
    glob = gamma_index(ref_img, ev_img, **kw)
    loc = gamma_index(ref_img, ev_img, local=True, **kw)
    g_glob, g_loc = glob.gamma[1, 1, deep], loc.gamma[1, 1, deep]
    # global: |ΔD| / (1 % of 1 Gy) = 2 in the high region, 0.6 in the low one; local: 2 in both
    assert np.allclose(g_glob, np.where(ref_1d[deep] == 1.0, 2.0, 0.6), atol=1e-12)
    assert np.allclose(g_loc, 2.0, atol=1e-12)
    thr = gamma_index(ref_img, ev_img, dose_percent=1, dta_mm=1, threshold_percent=50)
    assert thr.n_evaluated == 30 * 9  # only the high region is above 50 %


def test_gamma_sampling_reports_binomial_error():
    rng = np.random.default_rng(4)
    grid = ImageGrid((0, 0, 0), (2.0, 2.0, 2.0), np.eye(3), (20, 20, 20))
    ref = Image(rng.uniform(0.5, 1.0, grid.shape), grid)
    ev = Image(ref.array * rng.normal(1.0, 0.03, grid.shape), grid)
    full = gamma_index(ref, ev, dta_mm=0.5, max_gamma=1.0)
    part = gamma_index(ref, ev, dta_mm=0.5, max_gamma=1.0, max_points=2000, seed=5)
    assert part.sampled and part.n_evaluated == 2000 and part.pass_rate_std_percent > 0
    assert abs(part.pass_rate_percent - full.pass_rate_percent) < 4 * part.pass_rate_std_percent
    both = part.evaluated
    assert np.array_equal(part.gamma[both], full.gamma[both])


def test_gamma_agrees_with_pymedphys():
    pymedphys = pytest.importorskip("pymedphys", reason="pymedphys not installed (extra compare)")
    grid = ImageGrid((0, 0, 0), (2.0, 2.5, 3.0), np.eye(3), (16, 14, 10))
    k, j, i = np.meshgrid(*(np.arange(n) for n in grid.shape), indexing="ij")
    x, y, z = 2.0 * i, 2.5 * j, 3.0 * k
    ref = np.exp(-((x - 15) ** 2 + (y - 16) ** 2 + (z - 13) ** 2) / 200.0)
    ev = 1.03 * np.exp(-((x - 16.2) ** 2 + (y - 16) ** 2 + (z - 13.5) ** 2) / 190.0)
    ours = gamma_index(Image(ref, grid), Image(ev, grid), dose_percent=2, dta_mm=2,
                       threshold_percent=20, max_gamma=2.0, interp_fraction=10)
    axes = (3.0 * np.arange(10), 2.5 * np.arange(14), 2.0 * np.arange(16))
    theirs = pymedphys.gamma(axes, ref, axes, ev, 2, 2, lower_percent_dose_cutoff=20,
                             interp_fraction=10, max_gamma=2.0, local_gamma=False)
    both = np.isfinite(ours.gamma) & np.isfinite(theirs)
    assert both.sum() > 0.9 * ours.n_evaluated
    # both search a lattice of step Δd/10 (upper bounds of the continuous minimum); where the
    # gradient is steep (|∇D|·Δd/ΔD ≈ 3 here) a step shifts γ by up to ~0.15 either way
    diff = np.abs(ours.gamma[both] - theirs[both])
    assert diff.max() < 0.15 and diff.mean() < 0.02
    assert abs(ours.pass_rate_percent - 100 * np.mean(theirs[~np.isnan(theirs)] <= 1)) < 1.0


# --- DVH -----------------------------------------------------------------------------------------

def test_dvh_of_uniform_dose_is_a_step():
    h = dvh(np.full(500, 2.5), np.random.default_rng(6).uniform(0.1, 1.0, 500))
    m = h.metrics(v_gy=(2.4, 2.6))
    assert m["D95"] == m["D50"] == m["D2"] == m["Dmax"] == m["Dmin"] == 2.5
    assert np.isclose(m["Dmean"], 2.5)
    assert m["V2.4Gy"] == 100.0 and m["V2.6Gy"] == 0.0
    assert np.array_equal(h.curve(np.array([0.0, 2.5, 2.50001])), [100.0, 100.0, 0.0])


def test_d50_of_linear_dose_in_a_cube_is_the_mid_value():
    grid = ImageGrid((0, 0, 0), (1.0, 1.0, 1.0), np.eye(3), (40, 40, 40))
    dose = Image(np.broadcast_to(np.arange(40.0), grid.shape).copy(), grid)  # D = x
    h = image_dvh(dose, np.ones(grid.shape, bool))
    assert abs(h.dose_at_percent(50) - 19.5) <= 0.5
    assert abs(h.dose_at_percent(95) - 0.05 * 39) <= 1.0
    assert np.isclose(h.mean_gy, 19.5)
    assert np.isclose(h.volume_at_dose_percent(20.0), 50.0, rtol=1e-12)


def test_mesh_dvh_by_mass_and_volume():
    mesh = box_mesh()
    x = mesh.centroids_mm[:, 0]
    rho = np.where(mesh.points_mm[:, 0] > 20, 2.0, 1.0)
    by_vol = mesh_dvh(mesh, x, weight="volume")
    by_mass = mesh_dvh(mesh, x, weight="mass", density_g_cm3=rho)
    mass = tet_mass_g(mesh, rho)
    assert np.isclose(by_mass.mean_gy, np.dot(mass, x) / mass.sum())  # energy / mass
    assert np.isclose(by_vol.mean_gy, np.dot(mesh.volumes_mm3, x) / mesh.volumes_mm3.sum())
    assert by_mass.mean_gy > by_vol.mean_gy
    assert np.isclose(by_vol.total_weight, mesh.volumes_mm3.sum() / 1000.0)


# --- profiles ----------------------------------------------------------------------------------

def test_mesh_profile_is_piecewise_constant_per_tet(mesh_and_fields):
    mesh, _, dose = mesh_and_fields
    lo, hi = mesh.bounds_mm()
    prof = mesh_profile(mesh, dose, lo - 2.0, hi + 2.0, n=60)
    assert np.isnan(prof.dose_gy[0]) and np.isnan(prof.dose_gy[-1])
    for p, v in zip(prof.points_mm, prof.dose_gy, strict=True):
        owners = brute_force_locate(mesh, p)
        if len(owners):
            assert v in dose[owners]
    assert np.isclose(prof.distance_mm[-1], np.linalg.norm(hi - lo + 4.0))


def test_image_profile_is_trilinear():
    grid = ImageGrid((10, 0, 0), (2.0, 3.0, 4.0), np.eye(3), (10, 8, 6))
    k, j, i = np.meshgrid(*(np.arange(n) for n in grid.shape), indexing="ij")
    lin = lambda p: 1.0 + 0.1 * p[..., 0] - 0.05 * p[..., 1] + 0.02 * p[..., 2]  # noqa: E731
    centres = grid.voxel_centers_mm().reshape(*grid.shape, 3)
    img = Image(lin(centres), grid)
    prof = image_profile(img, (11.0, 1.0, 2.5), (26.0, 20.0, 19.0), n=30)
    assert np.allclose(prof.dose_gy, lin(prof.points_mm), atol=1e-12)
    outside = image_profile(img, (0.0, 0.0, 0.0), (5.0, 0.0, 0.0), n=5)
    assert np.all(np.isnan(outside.dose_gy))
    assert i.size == img.array.size


# --- CLI -----------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def dose_files(tmp_path_factory):
    from tetdose.core.io import write_image, write_mesh

    tmp = tmp_path_factory.mktemp("cmp")
    mesh = box_mesh()
    rho = np.random.default_rng(7).uniform(0.8, 1.2, mesh.n_points)
    dose = 1.0 + 0.02 * mesh.centroids_mm[:, 0]
    mesh = mesh.with_data(point_data={"density": rho}, cell_data={"dose": dose})
    write_mesh(tmp / "dose.vtu", mesh)
    grid = ImageGrid((0, 0, 0), (4.0, 4.0, 4.0), np.eye(3), (12, 10, 8))
    voxel = mesh_dose_to_grid(mesh, dose, grid, density_g_cm3=rho)
    write_image(tmp / "vdose.nrrd", voxel.with_array(1.01 * voxel.array))
    labels = np.zeros(grid.shape, np.int16)
    labels[2:6, 2:8, 2:6] = 1
    labels[2:6, 2:8, 6:10] = 2
    write_image(tmp / "labels.nrrd", Image(labels, grid))
    return tmp, mesh, dose, rho


def test_cli_compare_writes_report_with_numbers(dose_files, capsys):
    from tetdose.cli import main

    tmp, *_ = dose_files
    out = tmp / "report"
    assert main(["compare", "--mesh-dose", str(tmp / "dose.vtu"), "--voxel-dose",
                 str(tmp / "vdose.nrrd"), "--structures", str(tmp / "labels.nrrd"), "-q",
                 "-o", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    gam = summary["gamma"]
    assert gam["3%/3mm global"]["pass_rate_percent"] == 100.0  # a 1 % difference
    assert gam["3%/3mm local"]["pass_rate_percent"] == 100.0
    dvhs = summary["dvh"]
    assert set(dvhs) == {"mesh", "label 1", "label 2"}
    # label 2 lies at larger x, where the dose (rising along x) is higher
    assert dvhs["label 2"]["voxel"]["Dmean"] > dvhs["label 1"]["voxel"]["Dmean"]
    ratio = dvhs["label 1"]["voxel"]["Dmean"] / dvhs["label 1"]["mesh"]["Dmean"]
    assert abs(ratio - 1.01) < 0.01
    figures = json.loads((out / "figures.json").read_text())
    assert {"dvh", "profile_x", "profile_y", "profile_z"} <= set(figures)
    page = (out / "report.html").read_text()
    assert page.count("data:image/png;base64,") == len(figures)
    assert "pass" in capsys.readouterr().out


def test_cli_export_dose_round_trip_within_dose_grid_scaling(dose_files, tmp_path):
    import pydicom

    from tetdose.cli import main
    from tetdose.dicom.ct_series import write_ct_series

    tmp, mesh, dose, rho = dose_files
    ct_grid = ImageGrid((1.0, -2.0, 0.5), (3.0, 3.0, 5.0), np.eye(3), (18, 16, 9))
    ct_dir = tmp_path / "ct"
    write_ct_series(Image(np.zeros(ct_grid.shape, np.int16), ct_grid), ct_dir)
    out = tmp_path / "rtdose.dcm"
    assert main(["export-dose", "--dose", str(tmp / "dose.vtu"), "--like", str(ct_dir),
                 "-o", str(out)]) == 0
    ds = pydicom.dcmread(out)
    ct = pydicom.dcmread(next(ct_dir.glob("*.dcm")))
    assert ds.FrameOfReferenceUID == ct.FrameOfReferenceUID
    scaling = float(ds.DoseGridScaling)
    read_back = ds.pixel_array.astype(np.float64) * scaling
    expected = mesh_dose_to_grid(mesh, dose, ct_grid, density_g_cm3=rho).array
    assert read_back.shape == expected.shape
    assert np.abs(read_back - expected).max() <= 0.5 * scaling * (1 + 1e-6)
    assert expected.max() > 1.0
