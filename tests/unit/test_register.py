"""Registration on tiny synthetic CTs: identity, a known smooth field, Jacobians, the CLI chain."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from scipy import ndimage

from known_motion import breathing_field, warp
from tetdose.cli import main
from tetdose.core.image import Image, ImageGrid
from tetdose.core.io import read_image, write_mesh
from tetdose.dicom import write_ct_series_4d
from tetdose.errors import ImageError
from tetdose.motion.dvf import DisplacementField, read_dvf
from tetdose.motion.phases import PhaseSeries
from tetdose.motion.register import (
    RegistrationSettings,
    body_mask,
    jacobian_range,
    register,
    register_4dct,
)
from tetdose.phantoms import mesh_labels

GRID = ImageGrid([-40.0, -40.0, -30.0], [2.5, 2.5, 2.5], np.eye(3), (32, 32, 26))
FAST = RegistrationSettings(shrink=(2, 1), iterations=(60, 30), smoothing_mm=4.0)


def thorax(grid: ImageGrid = GRID) -> Image:
    """A textured body (≈ 0 HU) with a lung (≈ −800 HU) holding smooth 'vessels', in air."""
    rng = np.random.default_rng(7)
    p = grid.voxel_centers_mm().reshape(*grid.shape, 3)
    body = ((p[..., 0] / 34) ** 2 + (p[..., 1] / 32) ** 2) < 1
    lung = ((p[..., 0] / 22) ** 2 + (p[..., 1] / 20) ** 2 + ((p[..., 2] - 5) / 30) ** 2) < 1
    texture = ndimage.gaussian_filter(rng.normal(size=grid.shape), 1.5)
    hu = np.where(body, 40.0 + 600 * texture, -1000.0)
    hu = np.where(lung, -800.0 + 1500 * texture, hu)
    return Image(hu, grid)


def inner(grid: ImageGrid, margin_mm: float = 8.0) -> np.ndarray:
    """Voxels at least ``margin_mm`` from the image faces (motion there leaves the image)."""
    idx = np.indices(grid.shape)
    m = np.ones(grid.shape, dtype=bool)
    for a, n in enumerate(grid.shape):
        k = int(np.ceil(margin_mm / grid.spacing_mm[2 - a]))
        m &= (idx[a] >= k) & (idx[a] < n - k)
    return m


def test_identical_phases_give_zero_displacement():
    ct = thorax()
    out = register_4dct([ct, ct, ct], 1, percents=[0, 50, 80], settings=FAST)
    assert len(out) == 3
    for field, report in out:
        assert np.abs(field.vectors_mm).max() < 0.1
        assert not report.folded
    assert out[1][1].notes == ["reference phase: zero field"]
    assert out[0][1].metric_after_hu2 == pytest.approx(0.0, abs=1e-6)


def test_known_smooth_field_is_recovered():
    ct = thorax()
    u = breathing_field(5.0, diaphragm_z_mm=-20.0, centre_xy_mm=(0.0, 0.0),
                        width_xy_mm=(40.0, 40.0), decay_mm=60.0)
    phase = warp(ct, u)
    field, report = register(ct, phase, settings=FAST, percent=40.0, inverse_consistency=True)
    lung = (ct.array < -300) & (ct.array > -950) & inner(ct.grid)
    err = np.linalg.norm(field.vectors_mm - u(ct.grid.voxel_centers_mm()).reshape(field.vectors_mm.shape),
                         axis=-1)[lung]
    moved = np.linalg.norm(u(ct.grid.voxel_centers_mm()), axis=-1).reshape(ct.grid.shape)[lung]
    assert moved.mean() > 2.0  # the test moves the lung
    assert err.mean() < 0.5 * moved.mean() and err.mean() < 1.0
    assert report.metric_after_hu2 < 0.3 * report.metric_before_hu2
    assert report.folding_fraction == 0 and report.jacobian_min > 0
    assert report.percent == 40.0 and report.seconds > 0
    # the separately registered backward field undoes the forward one: |u(x) + w(x + u(x))|
    assert report.inverse_consistency_mean_mm < 0.5 and report.inverse_consistency_max_mm < 3.0


def test_jacobian_of_affine_and_folding_fields():
    p = GRID.voxel_centers_mm().reshape(*GRID.shape, 3)
    f = np.array([[0.1, 0.02, 0.0], [0.0, -0.2, 0.05], [0.03, 0.0, 0.15]])
    jac = jacobian_range(DisplacementField(p @ f.T, GRID), inner(GRID, 3.0))
    assert jac.min == pytest.approx(np.linalg.det(np.eye(3) + f), rel=1e-9)
    assert jac.max == pytest.approx(jac.min, rel=1e-9) and jac.folding_fraction == 0
    fold = np.zeros((*GRID.shape, 3))
    x = p[..., 0]
    fold[..., 0] = np.where(np.abs(x) < 10, -2.0 * x, -20.0 * np.sign(x))  # det = −1 in |x| < 10
    jac = jacobian_range(DisplacementField(fold, GRID))
    assert jac.min == pytest.approx(-1.0) and jac.max == pytest.approx(1.0)
    expected = np.mean(np.abs(x) < 10 - 1.25)  # central differences: one voxel each side blurs
    assert expected <= jac.folding_fraction <= np.mean(np.abs(x) < 10 + 1.25)
    assert abs(jac.worst_mm[0]) < 10


def test_body_mask_keeps_the_lung_when_it_touches_the_edge():
    ct = thorax()
    cut = Image(ct.array[:, :, :20], ImageGrid(ct.grid.origin_mm, ct.grid.spacing_mm,
                                                np.eye(3), (20, 32, 26)))  # lung cut by x-face
    mask = body_mask(cut)
    lung = (cut.array < -300) & (cut.array > -950)
    assert lung[:, :, -1].any() and mask[lung].all()
    assert not mask[0, 0, 0]  # air corner
    with pytest.raises(ImageError, match="holds no body"):
        body_mask(Image(np.full(GRID.shape, -1000.0), GRID))


def test_settings_are_checked():
    with pytest.raises(ImageError, match="one per level"):
        RegistrationSettings(shrink=(2, 1), iterations=(10,))
    with pytest.raises(ImageError, match="method"):
        RegistrationSettings(method="elastix")


def test_cli_register_deform_evaluate_chain(tmp_path):
    ct = thorax()
    u = breathing_field(4.0, diaphragm_z_mm=-20.0, centre_xy_mm=(0.0, 0.0),
                        width_xy_mm=(40.0, 40.0), decay_mm=60.0)
    phases = [ct.with_array(np.rint(ct.array).astype(np.int16)),
              ct.with_array(np.rint(warp(ct, u).array).astype(np.int16))]
    write_ct_series_4d(phases, tmp_path / "ct4d", phase_percent=[0.0, 50.0])
    args = ["--4dct", str(tmp_path / "ct4d"), "--reference", "0", "--shrink", "2", "1",
            "--iterations", "60", "30"]
    assert main(["register", "-q", *args, "-o", str(tmp_path / "dvf")]) == 0
    report = json.loads((tmp_path / "dvf" / "register.json").read_text())
    assert [p["percent"] for p in report["phases"]] == [0.0, 50.0]
    assert report["phases"][1]["metric_after_hu2"] < report["phases"][1]["metric_before_hu2"]
    fields = sorted((tmp_path / "dvf").glob("*.nrrd"))
    assert [f.name for f in fields] == ["phase_000.0.nrrd", "phase_050.0.nrrd"]
    assert np.abs(read_dvf(fields[0]).vectors_mm).max() == 0.0

    lung = ((ct.array < -300) & (ct.array > -950) & inner(ct.grid, 8.0)).astype(np.uint8)
    mesh = mesh_labels(Image(lung, ct.grid), target_edge_mm=10.0)
    rho = np.full(mesh.n_points, 0.3)
    write_mesh(tmp_path / "mapped.vtu", mesh.with_data(point_data={"density": rho}))
    assert main(["deform", "--mesh", str(tmp_path / "mapped.vtu"), "--dvf", *map(str, fields),
                 "-o", str(tmp_path / "ph")]) == 0
    series = PhaseSeries.read(None, tmp_path / "ph")
    np.testing.assert_array_equal(series.phase_percent, [0.0, 50.0])  # from register.json
    err = np.linalg.norm(series.points_mm[1] - mesh.points_mm - u(mesh.points_mm), axis=1)
    assert err.mean() < 1.0

    assert main(["deform", "-q", "--mesh", str(tmp_path / "mapped.vtu"), *args,
                 "-o", str(tmp_path / "one")]) == 0  # one step: register and deform
    one = PhaseSeries.read(None, tmp_path / "one")
    np.testing.assert_allclose(one.points_mm, series.points_mm, atol=1e-9)  # deterministic
    assert (tmp_path / "one" / "dvf" / "register.json").exists()

    assert main(["evaluate", "--phases", str(tmp_path / "ph"), "--4dct", str(tmp_path / "ct4d"),
                 "-o", str(tmp_path / "ev")]) == 0
    rows = json.loads((tmp_path / "ev" / "metrics.json").read_text())["phases"]
    assert [r["phase_percent"] for r in rows] == [0.0, 50.0]
    for r in rows:  # the mesh moved with the lung: its mass is the lung's in both phases
        assert r["mass_error_in_mesh_pct"] < 100.0 and np.isfinite(r["rmde_pct"])
    assert (tmp_path / "ev" / "phase_050.0.png").exists()

    # the real phase CTs as the bodies of the hybrid 4D dose, then the comparison
    (tmp_path / "plan.toml").write_text('[[beam]]\ntype = "parallel"\nenergy_mev = 1.25\n'
                                        'position_mm = [0.0, -200.0, 0.0]\n'
                                        'direction = [0.0, 1.0, 0.0]\nfield_mm = [40.0, 40.0]\n')
    assert main(["dose4d", "--physics", "kerma", "-q", "--phases", str(tmp_path / "ph"), "--ct4d",
                 str(tmp_path / "ct4d"), "--plan", str(tmp_path / "plan.toml"), "--histories",
                 "2e3", "-o", str(tmp_path / "d4")]) == 0
    d4 = json.loads((tmp_path / "d4" / "summary.json").read_text())
    assert d4["world"] == "hybrid" and all(p["lost_photons"] == 0 for p in d4["phases"])
    body = read_image(tmp_path / "d4" / "body" / "accumulated_combined.nrrd")
    assert body.grid.same_as(ct.grid) and body.array.max() > 0
    assert main(["compare", "-q", "--mesh-dose", str(tmp_path / "d4"), "--voxel-dose",
                 str(tmp_path / "d4" / "voxel" / "accumulated_energy_mass_transfer.nrrd"),
                 "-o", str(tmp_path / "cmp")]) == 0
    assert json.loads((tmp_path / "cmp" / "summary.json").read_text())["region"]["voxels"] > 0
    assert main(["evaluate", "--phases", str(tmp_path / "ph"), "-o", str(tmp_path / "x")]) == 2


def test_folding_is_reported_as_a_one_line_error(capsys):
    from tetdose.cli._register import print_reports
    from tetdose.motion.register import RegistrationReport

    ok = RegistrationReport(0.0, 1.0, 0.5, 0.9, 1.1, 0.0, (0.0, 0.0, 0.0), 3.0, 1.0)
    bad = RegistrationReport(20.0, 1.0, 0.5, -0.4, 1.3, 0.0123, (1.0, -2.5, 30.0), 9.0, 1.0)
    assert print_reports([ok], "register") == 0
    assert print_reports([ok, bad], "register") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert "phase 20 %" in err[0] and "1.23 %" in err[0] and "(1.0, -2.5, 30.0) mm" in err[0]


def test_cli_register_with_a_mask_file(tmp_path):
    from tetdose.core.io import write_image

    ct = thorax()
    same = ct.with_array(np.rint(ct.array).astype(np.int16))
    files = [str(write_image(tmp_path / f"phase_{p:05.1f}.nrrd", same)) for p in (50.0, 0.0)]
    lung = ((ct.array < -300) & (ct.array > -950)).astype(np.uint8)
    write_image(tmp_path / "lung.nii.gz", Image(lung, ct.grid))
    assert main(["register", "-q", "--4dct", *files, "--reference", "50",
                 "--mask", str(tmp_path / "lung.nii.gz"), "--shrink", "1", "--iterations", "10",
                 "-o", str(tmp_path / "dvf")]) == 0
    report = json.loads((tmp_path / "dvf" / "register.json").read_text())
    assert report["reference_percent"] == 50.0
    assert [p["percent"] for p in report["phases"]] == [0.0, 50.0]  # files sorted by name %
    assert all(np.abs(read_dvf(f).vectors_mm).max() < 0.1
               for f in (tmp_path / "dvf").glob("*.nrrd"))  # identical phases
    write_image(tmp_path / "empty.nii.gz", Image(0 * lung, ct.grid))
    assert main(["register", "-q", "--4dct", *files, "--reference", "50",
                 "--mask", str(tmp_path / "empty.nii.gz"), "-o", str(tmp_path / "x")]) == 2
    assert not (tmp_path / "x").exists()  # nothing half-written


def test_crop_to_the_masks_box_keeps_the_field_and_continues_it_outside():
    from tetdose.motion.register import _crop_box

    small = thorax()
    pad = 12  # air around the body: the box (body + 20 mm) is smaller than the image in x, y
    arr = np.pad(small.array, ((0, 0), (pad, pad), (pad, pad)), constant_values=-1000.0)
    grid = ImageGrid(GRID.origin_mm - [pad * 2.5, pad * 2.5, 0.0], GRID.spacing_mm, np.eye(3),
                     (arr.shape[2], arr.shape[1], arr.shape[0]))
    ct = Image(arr, grid)
    u = breathing_field(5.0, diaphragm_z_mm=-20.0, centre_xy_mm=(0.0, 0.0),
                        width_xy_mm=(40.0, 40.0), decay_mm=60.0)
    phase = warp(ct, u)
    cropped, _ = register(ct, phase, settings=FAST)
    whole, _ = register(ct, phase, settings=RegistrationSettings(
        shrink=FAST.shrink, iterations=FAST.iterations, smoothing_mm=4.0, crop_margin_mm=None))
    lung = (ct.array < -300) & (ct.array > -950) & inner(grid)
    true = u(grid.voxel_centers_mm()).reshape(cropped.vectors_mm.shape)
    err = np.linalg.norm(cropped.vectors_mm - true, axis=-1)[lung]
    assert err.mean() < 1.0
    diff = np.linalg.norm(cropped.vectors_mm - whole.vectors_mm, axis=-1)[lung]
    assert diff.mean() < 0.1 * np.linalg.norm(true, axis=-1)[lung].mean()  # same field inside
    body = body_mask(ct) | body_mask(phase)
    box = _crop_box(body, grid.spacing_mm[::-1], 20.0)
    assert box[2].start > 0 and box[2].stop < arr.shape[2]  # the crop is real
    v = cropped.vectors_mm
    np.testing.assert_array_equal(v[:, :, : box[2].start], np.repeat(
        v[:, :, box[2].start: box[2].start + 1], box[2].start, axis=2))  # edge replication
    np.testing.assert_array_equal(v[:, : box[1].start, box[2]], np.repeat(
        v[:, box[1].start: box[1].start + 1, box[2]], box[1].start, axis=1))


def test_warm_start_starts_from_the_given_field():
    ct = thorax()
    u = breathing_field(5.0, diaphragm_z_mm=-20.0, centre_xy_mm=(0.0, 0.0),
                        width_xy_mm=(40.0, 40.0), decay_mm=60.0)
    phase = warp(ct, u)
    true = DisplacementField(u(ct.grid.voxel_centers_mm()).reshape(*ct.grid.shape, 3), ct.grid)
    one = RegistrationSettings(shrink=(2, 1), iterations=(1, 1), smoothing_mm=4.0)
    lung = (ct.array < -300) & (ct.array > -950) & inner(ct.grid)
    warm, _ = register(ct, phase, settings=one, initial=true)
    cold, _ = register(ct, phase, settings=one)
    err = {k: np.linalg.norm(f.vectors_mm - true.vectors_mm, axis=-1)[lung].mean()
           for k, f in (("warm", warm), ("cold", cold))}
    assert err["warm"] < 0.5 < 2.0 < err["cold"]  # one iteration: only the start tells them apart
    with pytest.raises(ImageError, match="initial field"):
        register(ct, phase, settings=one, initial=DisplacementField(
            np.zeros((*GRID.shape, 3)), ImageGrid(GRID.origin_mm + 1.0, GRID.spacing_mm,
                                                  np.eye(3), GRID.size)))


def test_4dct_warm_start_registers_outward_and_recovers_every_phase():
    ct = thorax()
    amps = [4.0, 2.0, 0.0, 2.0, 5.0]  # reference in the middle, motion growing outward
    us = [breathing_field(max(a, 1e-9), diaphragm_z_mm=-20.0, centre_xy_mm=(0.0, 0.0),
                          width_xy_mm=(40.0, 40.0), decay_mm=60.0) for a in amps]
    phases = [ct if a == 0 else warp(ct, u) for a, u in zip(amps, us, strict=True)]
    lung = (ct.array < -300) & (ct.array > -950) & inner(ct.grid)
    settings = RegistrationSettings(shrink=(2, 1), iterations=(60, 30), smoothing_mm=4.0)
    for warm in (True, False):
        out = register_4dct(phases, 2, settings=replace(settings, warm_start=warm))
        for (field, report), u, a in zip(out, us, amps, strict=True):
            true = u(ct.grid.voxel_centers_mm()).reshape(field.vectors_mm.shape)
            err = np.linalg.norm(field.vectors_mm - true, axis=-1)[lung]
            assert err.mean() < max(0.1, 0.15 * a), (warm, a, err.mean())
            assert not report.folded


def test_hull_rows_match_the_pixelwise_half_plane_test():
    from scipy.spatial import ConvexHull

    from tetdose.motion.register import _hull_rows

    rng = np.random.default_rng(3)
    ny, nx = 40, 55
    jj, ii = np.mgrid[0:ny, 0:nx]
    pix = np.stack([ii.ravel(), jj.ravel()], axis=1).astype(np.float64)
    for pts in (rng.uniform([5, 3], [50, 36], size=(30, 2)),  # random polygon
                np.array([[10.0, 5.0], [40.0, 5.0], [40.0, 30.0], [10.0, 30.0]])):  # a = 0 facets
        eq = ConvexHull(pts).equations
        brute = np.all(pix @ eq[:, :2].T + eq[:, 2] <= 0.5, axis=1).reshape(ny, nx)
        np.testing.assert_array_equal(_hull_rows(eq, ny, nx), brute)
        assert brute.sum() > 100


def test_cli_crop_and_warm_start_options_reach_the_settings():
    import argparse

    from tetdose.cli._register import add_args, settings_from

    p = argparse.ArgumentParser()
    add_args(p)
    base = ["--4dct", "ct4d", "--reference", "50", "-o", "dvf"]
    d = settings_from(p.parse_args(base))
    assert d.crop_margin_mm == RegistrationSettings().crop_margin_mm and d.warm_start
    s = settings_from(p.parse_args([*base, "--crop-margin-mm", "5", "--no-warm-start"]))
    assert s.crop_margin_mm == 5.0 and not s.warm_start
    assert settings_from(p.parse_args([*base, "--no-crop"])).crop_margin_mm is None
    with pytest.raises(ImageError, match="crop_margin_mm"):
        RegistrationSettings(crop_margin_mm=-1.0)


def test_register_to_folder_writes_fields_and_report_that_percents_of_reads(tmp_path):
    """The library workflow behind ``tetdose register``: fields named by phase, the report
    listing them, and ``percents_of`` giving back the percents only for one such folder."""
    from tetdose.core.io import write_image
    from tetdose.motion.dvf_folder import REPORT_NAME, percents_of, register_to_folder

    ct = thorax()
    same = ct.with_array(np.rint(ct.array).astype(np.int16))
    files = [write_image(tmp_path / f"phase_{p:05.1f}.nrrd", same) for p in (20.0, 70.0)]
    fast = replace(FAST, iterations=(10, 5))
    out, percents, reports = register_to_folder(files, 70.0, tmp_path / "dvf", settings=fast,
                                                progress=False)
    assert percents == [20.0, 70.0] and [f.name for f in out] == ["phase_020.0.nrrd",
                                                                   "phase_070.0.nrrd"]
    assert all(f.exists() and np.abs(read_dvf(f).vectors_mm).max() < 0.1 for f in out)
    doc = json.loads((tmp_path / "dvf" / REPORT_NAME).read_text())
    assert doc["reference_percent"] == 70.0 and doc["settings"]["iterations"] == [10, 5]
    assert [r.as_dict()["percent"] for r in reports] == [20.0, 70.0]
    assert percents_of(out[::-1]) == [70.0, 20.0]  # in the order given
    stray = tmp_path / "elsewhere.nrrd"
    stray.write_bytes(out[0].read_bytes())
    assert percents_of([out[0], stray]) is None  # not all from one register folder
