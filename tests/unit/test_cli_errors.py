"""Bad input through the command line: exit code 2, one line on stderr naming the problem and the
fix, no traceback, no output written, inputs untouched (bytes and mtime).

Each row of :data:`CASES` is (id, argv with ``{d}`` = the shared input folder and ``{o}`` = this
case's output folder, words the message must hold). Inputs are built once per module, small.
"""

from __future__ import annotations

import os
from pathlib import Path

import meshio
import numpy as np
import pydicom
import pytest
import SimpleITK as sitk

from tetdose.calibration import HUCalibration
from tetdose.cli import build_parser, main
from tetdose.dicom.ct_series import write_ct_series
from tetdose.image import Image
from tetdose.io import write_image, write_mesh

from helpers import box_mesh, density_image, grid_for

CAL = HUCalibration.schneider2000()


def _raw_mesh(path: Path, points: np.ndarray, cells: list, **point_data: np.ndarray) -> None:
    meshio.write(path, meshio.Mesh(points, cells, point_data=point_data))


def _dicom_variant(src: list[Path], out: Path, edit) -> None:  # noqa: ANN001
    """Copy a DICOM series into ``out`` with ``edit(dataset, k)`` applied to slice k
    (``edit`` returning False drops the slice)."""
    out.mkdir()
    for k, f in enumerate(src):
        ds = pydicom.dcmread(f)
        if edit(ds, k) is not False:
            ds.save_as(out / f.name)


@pytest.fixture(scope="module")
def d(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("inputs")
    grid = grid_for([0, 0, 0], [24, 20, 16], [2.0, 2.0, 2.0])
    rho = density_image(grid, lambda x, y, z: np.where(x < 12, 0.26, 1.05) + 0.002 * y)
    ct = rho.with_array(np.round(CAL.hu_of(rho.array)).astype(np.int16))
    write_image(d / "ct.nrrd", ct)
    write_image(d / "ct_u16.nrrd", ct.with_array(ct.array.astype(np.uint16)))  # wrapped HU
    write_image(d / "ct_i8.nrrd", ct.with_array(np.clip(ct.array, -128, 127).astype(np.int8)))
    nan_ct = ct.array.astype(np.float32)
    nan_ct[3, 4, 5] = np.nan
    write_image(d / "ct_nan.nrrd", ct.with_array(nan_ct))
    sitk.WriteImage(sitk.GetImageFromArray(np.zeros((5, 6), np.int16)), str(d / "ct_2d.nrrd"))
    frame = sitk.GetImageFromArray(np.zeros((3, 4, 5), np.int16))
    sitk.WriteImage(sitk.JoinSeries([frame, frame]), str(d / "ct_4d.nrrd"))
    (d / "empty.nrrd").write_bytes(b"")
    (d / "garbage.nrrd").write_bytes(np.random.default_rng(0).bytes(300))

    mesh = box_mesh([3, 3, 2], [21, 17, 14], (3, 3, 2), jitter=0.2)
    write_mesh(d / "mesh.vtu", mesh)
    vtu = (d / "mesh.vtu").read_bytes()
    (d / "empty.vtu").write_bytes(b"")
    (d / "truncated.vtu").write_bytes(vtu[: len(vtu) // 2])
    (d / "garbage.vtu").write_bytes(np.random.default_rng(1).bytes(500))
    pts, tets = mesh.points_mm, mesh.tets
    _raw_mesh(d / "triangles.vtu", pts, [("triangle", tets[:, :3])])
    nan_pts = pts.copy()
    nan_pts[5] = np.nan
    _raw_mesh(d / "nan_points.vtu", nan_pts, [("tetra", tets)])
    inverted = tets.copy()
    inverted[0, [0, 1]] = inverted[0, [1, 0]]
    _raw_mesh(d / "inverted.vtu", pts, [("tetra", inverted)])
    flat = np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0], [5, 5, 0], [0, 0, 10.0]]) + 4
    _raw_mesh(d / "flat.vtu", flat, [("tetra", np.array([[0, 1, 2, 4], [0, 1, 2, 3]]))])
    far_pts = pts.copy()
    far_pts[np.argmax(pts[:, 0])] = [1e12, 0, 0]
    _raw_mesh(d / "far_point.vtu", far_pts, [("tetra", tets)])
    write_mesh(d / "outside.vtu", box_mesh([500, 500, 500], [510, 510, 510], (1, 1, 1)))
    ones = np.ones(mesh.n_points)
    write_mesh(d / "mapped.vtu", mesh.with_data(point_data={"density": ones}))
    nan_rho = ones.copy()
    nan_rho[7] = np.nan
    write_mesh(d / "nan_density.vtu", mesh.with_data(point_data={"density": nan_rho}))
    write_mesh(d / "neg_density.vtu", mesh.with_data(point_data={"density": ones - 2.0}))
    (d / "bad_cal.csv").write_text("HU,density\n0,1.0\n-100,0.9\n")

    series = write_ct_series(Image(ct.array, ct.grid), d / "dicom_ok")
    _dicom_variant(series, d / "dicom_missing", lambda ds, k: k != 3)
    _dicom_variant(series, d / "dicom_mr", lambda ds, k: setattr(ds, "Modality", "MR"))
    _dicom_variant(series, d / "dicom_slope0", lambda ds, k: setattr(ds, "RescaleSlope", "0"))

    def shear(ds, k):  # noqa: ANN001, ANN202 - a gantry tilt: slices shift along y
        pos = [float(v) for v in ds.ImagePositionPatient]
        ds.ImagePositionPatient = [pos[0], pos[1] + 0.35 * k, pos[2]]

    _dicom_variant(series, d / "dicom_sheared", shear)
    _dicom_variant(series, d / "dicom_skewed", lambda ds, k: setattr(
        ds, "ImageOrientationPatient", [1, 0, 0, 0.2, 0.98, 0]))
    return d


MAP = ["map", "-q", "--ct", "{d}/ct.nrrd", "--mesh", "{d}/mesh.vtu", "-o", "{o}/out.vtu"]


def _map(**change: str) -> list[str]:
    argv = list(MAP)
    for flag, value in change.items():
        argv[argv.index(f"--{flag}") + 1] = value
    return argv


VOX = ["voxelize", "-q", "--mesh", "{d}/mapped.vtu", "--like", "{d}/ct.nrrd",
       "-o", "{o}/vct.nrrd"]
EVAL = ["evaluate", "-q", "--ct", "{d}/ct.nrrd", "--mesh", "{d}/mapped.vtu", "-o", "{o}/report"]

CASES = [
    # --- map: meshes
    ("map-empty-mesh", _map(mesh="{d}/empty.vtu"), ["is empty", "VTU"]),
    ("map-truncated-mesh", _map(mesh="{d}/truncated.vtu"), ["cannot read mesh"]),
    ("map-garbage-mesh", _map(mesh="{d}/garbage.vtu"), ["cannot read mesh"]),
    ("map-triangles-only", _map(mesh="{d}/triangles.vtu"), ["no tetrahedra", "mesh the surface"]),
    ("map-nan-points", _map(mesh="{d}/nan_points.vtu"), ["NaN", "fix the mesh"]),
    ("map-inverted-tets", _map(mesh="{d}/inverted.vtu"), ["inverted", "--fix-orientation"]),
    ("map-zero-volume-tet", _map(mesh="{d}/flat.vtu"), ["degenerate", "remesh"]),
    ("map-point-at-1e12", _map(mesh="{d}/far_point.vtu"), ["km from the origin", "in mm"]),
    ("map-mesh-outside-ct", _map(mesh="{d}/outside.vtu"), ["wholly outside", "patient"]),
    ("map-missing-mesh", _map(mesh="{d}/nope.vtu"), ["does not exist"]),
    # --- map: CTs
    ("map-missing-ct", _map(ct="{d}/nope.nrrd"), ["does not exist"]),
    ("map-empty-ct", _map(ct="{d}/empty.nrrd"), ["cannot read image"]),
    ("map-garbage-ct", _map(ct="{d}/garbage.nrrd"), ["cannot read image"]),
    ("map-2d-image", _map(ct="{d}/ct_2d.nrrd"), ["3-D image", "2-D"]),
    ("map-4d-image", _map(ct="{d}/ct_4d.nrrd"), ["3-D image", "4-D"]),
    ("map-uint16-ct", _map(ct="{d}/ct_u16.nrrd"), ["uint16", "signed HU"]),
    ("map-int8-ct", _map(ct="{d}/ct_i8.nrrd"), ["int8", "signed HU"]),
    ("map-nan-voxel", _map(ct="{d}/ct_nan.nrrd"), ["NaN", "i=5, j=4, k=3", "−1000 HU"]),
    ("map-dicom-missing-slice", _map(ct="{d}/dicom_missing"), ["not uniform", "missing"]),
    ("map-dicom-mr", _map(ct="{d}/dicom_mr"), ["modality", "MR", "CT series"]),
    ("map-dicom-sheared", _map(ct="{d}/dicom_sheared"), ["gantry tilt", "not resampled"]),
    ("map-dicom-slope-0", _map(ct="{d}/dicom_slope0"), ["RescaleSlope 0", "fix the series"]),
    ("map-dicom-skewed", _map(ct="{d}/dicom_skewed"), ["not orthonormal"]),
    ("map-bad-calibration", MAP + ["--calibration", "{d}/bad_cal.csv"], ["increasing"]),
    # --- map: options and output, checked before any work
    ("map-samples-negative", MAP + ["--overlap", "monte-carlo", "--samples", "-10"],
     ["--samples", "≥ 1", "-10"]),
    ("map-samples-zero", MAP + ["--overlap", "monte-carlo", "--samples", "0"], ["--samples", "≥ 1"]),
    ("map-samples-word", MAP + ["--samples", "many"], ["--samples", "whole number"]),
    ("map-unknown-extension", _map(ct="{d}/nope.nrrd")[:-1] + ["{o}/out.xyz"],
     ["unknown extension", ".vtu"]),
    ("map-output-is-input", _map()[:-1] + ["{d}/mesh.vtu"], ["also an input"]),
    ("map-output-is-folder", _map()[:-1] + ["{d}"], ["is a folder"]),
    # --- voxelize
    ("voxelize-background-negative", VOX + ["--background", "-3"], ["--background", "≥ 0"]),
    ("voxelize-background-word", VOX + ["--background", "water"], ["--background", "air, ct"]),
    ("voxelize-background-nan", VOX + ["--background", "nan"], ["--background", "finite"]),
    ("voxelize-overwrites-like", VOX[:-1] + ["{d}/ct.nrrd"], ["also an input"]),
    ("voxelize-unknown-extension", VOX[:-1] + ["{o}/vct.vtu"], ["unknown extension", ".nrrd"]),
    ("voxelize-nan-density", ["voxelize", "--mesh", "{d}/nan_density.vtu", "--like",
                              "{d}/ct.nrrd", "-o", "{o}/vct.nrrd"], ["NaN", "tetdose map"]),
    ("voxelize-negative-density", ["voxelize", "--mesh", "{d}/neg_density.vtu", "--like",
                                   "{d}/ct.nrrd", "-o", "{o}/vct.nrrd"], ["negative", "--solver l2"]),
    ("voxelize-unmapped-mesh", ["voxelize", "--mesh", "{d}/mesh.vtu", "--like", "{d}/ct.nrrd",
                                "-o", "{o}/vct.nrrd"], ["no point_data 'density'", "tetdose map"]),
    ("voxelize-background-ct-uint16", ["voxelize", "--mesh", "{d}/mapped.vtu", "--like",
                                       "{d}/ct_u16.nrrd", "--background", "ct", "-o",
                                       "{o}/vct.nrrd"], ["uint16", "--background ct"]),
    # --- evaluate (its module is another issue's; the checks it reaches are ours)
    ("evaluate-nan-density", ["evaluate", "--ct", "{d}/ct.nrrd", "--mesh", "{d}/nan_density.vtu",
                              "-o", "{o}/report"], ["NaN", "tetdose map"]),
    ("evaluate-uint16-ct", EVAL[:3] + ["{d}/ct_u16.nrrd"] + EVAL[4:], ["uint16"]),
    # --- phantom
    ("phantom-seed-negative", ["phantom", "cube", "--size", "small", "--seed", "-1", "-o",
                               "{o}/ph"], ["--seed", "≥ 0"]),
    ("phantom-unknown-name", ["phantom", "sphere-of-cheese", "-o", "{o}/ph"], ["invalid choice"]),
    ("phantom-output-is-input-folder", ["phantom", "cube", "--size", "small", "-o", "{d}"],
     ["holds files tetdose did not write", "--overwrite"]),
]


def _snapshot(folder: Path) -> dict[str, tuple[bytes, int]]:
    return {str(p.relative_to(folder)): (p.read_bytes(), p.stat().st_mtime_ns)
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.mark.parametrize(("argv", "words"), [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_bad_input_is_one_line_and_writes_nothing(d, tmp_path, capsys, argv, words):
    out = tmp_path / "out"
    out.mkdir()
    before = _snapshot(d)
    code = main([a.format(d=d, o=out) for a in argv])
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip() and ": warning:" not in ln]
    assert code == 2, err
    assert len(lines) == 1, err
    assert "Traceback" not in err and lines[0].startswith(f"tetdose {argv[0]}: error: "), err
    for word in words:
        assert word in lines[0], (word, lines[0])
    assert list(out.iterdir()) == [], "an output was written"
    assert _snapshot(d) == before, "an input was changed"


def test_existing_file_as_output_folder(d, tmp_path, capsys):
    """evaluate and phantom given an existing file for -o: one line, the file kept."""
    blocker = tmp_path / "taken"
    blocker.write_bytes(b"precious")
    for argv in (EVAL[:-1] + [str(blocker)], ["phantom", "cube", "--size", "small", "-o",
                                             str(blocker)]):
        code = main([a.format(d=d, o=tmp_path) for a in argv])
        err = capsys.readouterr().err.strip()
        assert code == 2 and len(err.splitlines()) == 1 and "existing file" in err, err
        assert blocker.read_bytes() == b"precious"


def test_current_folder_as_output_is_refused(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "keep.txt").write_text("mine")
    assert main(["phantom", "cube", "--size", "small", "-o", "."]) == 2
    err = capsys.readouterr().err.strip()
    assert "current folder" in err and "-o out" in err and len(err.splitlines()) == 1
    assert [p.name for p in tmp_path.iterdir()] == ["keep.txt"]


def test_foreign_folder_needs_overwrite_and_own_output_does_not(tmp_path, capsys):
    out = tmp_path / "ph"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    assert main(["phantom", "cube", "--size", "small", "-q", "-o", str(out)]) == 2
    assert "--overwrite" in capsys.readouterr().err and (out / "notes.txt").exists()
    assert main(["phantom", "cube", "--size", "small", "-q", "-o", str(out), "--overwrite"]) == 0
    assert not (out / "notes.txt").exists() and (out / "mesh.vtu").exists()
    mtime = (out / "mesh.vtu").stat().st_mtime_ns
    assert main(["phantom", "cube", "--size", "small", "-q", "-o", str(out)]) == 0  # ours: rerun
    assert (out / "mesh.vtu").stat().st_mtime_ns >= mtime
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ph"]  # no temporary left beside it


def test_unwritable_output_folder_is_one_line(d, tmp_path, capsys, monkeypatch):
    """A read-only folder (simulated: the tests may run as root, who may write anywhere)."""
    real_access = os.access
    monkeypatch.setattr(os, "access", lambda p, mode, **kw: False if Path(p) == tmp_path
                        else real_access(p, mode, **kw))
    code = main([a.format(d=d, o=tmp_path) for a in MAP])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and "permission denied" in err, err
    assert list(tmp_path.iterdir()) == []


def test_os_errors_during_the_write_are_one_line(d, tmp_path, capsys, monkeypatch):
    import errno
    import tempfile

    def full(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(tempfile, "mkstemp", full)
    code = main(["phantom", "cube", "--size", "small", "-q", "-o", str(tmp_path / "ph")])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and "no space left" in err, err
    assert list(tmp_path.iterdir()) == []


def test_debug_shows_the_traceback(d, tmp_path, capsys):
    argv = [a.format(d=d, o=tmp_path) for a in _map(mesh="{d}/inverted.vtu")]
    assert main(["--debug", *argv]) == 2
    err = capsys.readouterr().err
    assert "Traceback" in err and err.strip().splitlines()[-1].startswith("tetdose map: error:")


def test_warnings_print_as_one_line_without_source_paths(d, tmp_path, capsys, monkeypatch):
    import sys
    import warnings

    # pytest records warnings itself; print them as Python does outside pytest
    monkeypatch.setattr(warnings, "_showwarnmsg_impl",
                        lambda msg: sys.stderr.write(warnings._formatwarnmsg(msg)))
    monkeypatch.setattr(warnings, "filters", [("always", None, Warning, None, 0)])
    write_mesh(tmp_path / "half.vtu", box_mesh([12, 3, 2], [36, 17, 14], (2, 1, 1)))
    assert main(["map", "-q", "--ct", str(d / "ct.nrrd"), "--mesh", str(tmp_path / "half.vtu"),
                 "-o", str(tmp_path / "m.vtu")]) == 0
    err = capsys.readouterr().err.strip()
    assert err.startswith("tetdose map: warning:") and "outside the image" in err
    assert len(err.splitlines()) == 1 and ".py" not in err


def test_help_shows_no_developer_remarks(capsys):
    assert main(["--help"]) == 0
    text = capsys.readouterr().out
    assert "meshio" not in text and "_cli" not in text and "--debug" in text
    sub = build_parser()._subparsers._group_actions[0].choices  # noqa: SLF001
    assert "--overwrite" in sub["phantom"].format_help()


def test_lsq_undershoot_is_warned_by_map_and_refused_by_voxelize(d, tmp_path, capsys,
                                                                 monkeypatch):
    import sys
    import warnings

    monkeypatch.setattr(warnings, "_showwarnmsg_impl",
                        lambda msg: sys.stderr.write(warnings._formatwarnmsg(msg)))
    monkeypatch.setattr(warnings, "filters", [("always", None, Warning, None, 0)])
    # air (−1000 HU) next to bone: the paper's least squares undershoots below 0 g/cm³
    grid = grid_for([0, 0, 0], [24, 20, 16], [2.0, 2.0, 2.0])
    edge = density_image(grid, lambda x, y, z: np.where(x < 11, -1000.0, 1500.0))
    write_image(tmp_path / "edge.nrrd", edge.with_array(edge.array.astype(np.int16)))
    assert main(["map", "-q", "--solver", "lsq", "--ct", str(tmp_path / "edge.nrrd"), "--mesh",
                 str(d / "mesh.vtu"), "-o", str(tmp_path / "lsq.vtu")]) == 0
    err = capsys.readouterr().err
    assert "tetdose map: warning:" in err and "negative" in err and "--solver l2" in err
    assert main(["voxelize", "--mesh", str(tmp_path / "lsq.vtu"), "--like", str(d / "ct.nrrd"),
                 "-o", str(tmp_path / "v.nrrd")]) == 2
    assert "negative" in capsys.readouterr().err and not (tmp_path / "v.nrrd").exists()


def test_every_folder_writing_command_takes_overwrite(tmp_path, capsys):
    from tetdose.cli import FOLDER_OUTPUTS

    sub = build_parser()._subparsers._group_actions[0].choices  # noqa: SLF001
    for name in FOLDER_OUTPUTS:
        assert "--overwrite" in sub[name].format_help(), name
    out = tmp_path / "phases"
    out.mkdir()
    (out / "thesis.tex").write_text("mine")
    write_mesh(tmp_path / "m.vtu", box_mesh([0, 0, 0], [4, 4, 4], (1, 1, 1)).with_data(
        point_data={"density": np.ones(8)}))
    argv = ["deform", "-q", "--mesh", str(tmp_path / "m.vtu"), "--breathing", "--n-phases", "2",
            "-o", str(out)]
    assert main(argv) == 2 and "--overwrite" in capsys.readouterr().err
    assert (out / "thesis.tex").exists()
    assert main([*argv, "--overwrite"]) == 0 and not (out / "thesis.tex").exists()
