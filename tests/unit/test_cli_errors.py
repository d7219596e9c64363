"""Bad input through the command line: exit code 2, one line on stderr naming the problem and the
fix, no traceback, no output written, inputs untouched (bytes and mtime).

Each row of :data:`CASES` is (id, argv with ``{d}`` = the shared input folder and ``{o}`` = this
case's output folder, words the message must hold). Inputs are built once per module, small.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from cli_inputs import build
from tetdose.cli import build_parser, main
from tetdose.core.io import write_image, write_mesh

from helpers import box_mesh, density_image, grid_for


@pytest.fixture(scope="module")
def d(tmp_path_factory) -> Path:
    return build(tmp_path_factory.mktemp("inputs"))


MAP = ["map", "-q", "--ct", "{d}/ct.nrrd", "--mesh", "{d}/mesh.vtu", "-o", "{o}/out.vtu"]


def _with(base: list[str], **change: str) -> list[str]:
    """``base`` with the value after ``--FLAG`` replaced for each FLAG=value."""
    argv = list(base)
    for flag, value in change.items():
        argv[argv.index(f"--{flag}") + 1] = value
    return argv


def _map(**change: str) -> list[str]:
    return _with(MAP, **change)


VOX = ["voxelize", "-q", "--mesh", "{d}/mapped.vtu", "--like", "{d}/ct.nrrd",
       "-o", "{o}/vct.nrrd"]
DEFORM = ["deform", "-q", "--mesh", "{d}/mapped.vtu", "--breathing", "--n-phases", "2", "-o",
          "{o}/ph"]
V4D = ["4dct", "-q", "--phases", "{d}/phases", "--like", "{d}/ct.nrrd", "-o", "{o}/v4"]
DOSE = ["dose", "-q", "--mesh", "{d}/mapped.vtu", "--plan", "{d}/plan.toml", "--histories", "2000",
        "--batches", "2", "-o", "{o}/dose.vtu"]
DOSE_CT = ["dose", "--ct", "{d}/ct.nrrd", "--plan", "{d}/plan.toml", "--histories", "2000",
           "-o", "{o}/dose.nrrd"]
DOSE4D = ["dose4d", "-q", "--phases", "{d}/phases", "--plan", "{d}/plan.toml", "--histories",
          "2000", "--batches", "2", "-o", "{o}/d4"]
CMP = ["compare", "-q", "--mesh-dose", "{d}/dose.vtu", "--voxel-dose", "{d}/dose.nrrd", "-o",
       "{o}/cmp"]
EXPORT = ["export-dose", "-q", "--dose", "{d}/dose.vtu", "--like", "{d}/ct.nrrd", "-o",
          "{o}/rd.dcm"]
REG = ["register", "-q", "--4dct", "{d}/ct.nrrd", "{d}/ct_coarse.nrrd", "--reference", "0", "-o",
       "{o}/reg"]
EVAL = ["evaluate", "-q", "--ct", "{d}/ct.nrrd", "--mesh", "{d}/mapped.vtu", "-o", "{o}/report"]
DOSE_RT = ["dose", "-q", "--ct", "{d}/dicom_ok", "--rtplan", "{d}/rtplan.dcm", "--histories",
           "2000", "--batches", "2", "-o", "{o}/dose.nrrd"]
HYBRID = DOSE + ["--ct", "{d}/ct.nrrd"]
MESH = ["mesh", "-q", "--labels", "{d}/labels.nrrd", "-o", "{o}/m.vtu"]
MESH_RS = ["mesh", "-q", "--structures", "{d}/rs.dcm", "--roi", "GTV", "--ct", "{d}/dicom_ok",
           "-o", "{o}/m.vtu"]

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
    ("map-dicom-sheared", _map(ct="{d}/dicom_sheared"), ["gantry tilt", "not resampled",
                                                         "--resample-tilted"]),
    ("map-dicom-slope-0", _map(ct="{d}/dicom_slope0"), ["RescaleSlope 0", "fix the series"]),
    ("map-dicom-skewed", _map(ct="{d}/dicom_skewed"), ["not orthonormal", "--resample-tilted"]),
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
    ("evaluate-negative-density", EVAL[:5] + ["{d}/neg_density.vtu"] + EVAL[6:],
     ["negative", "--solver l2"]),
    ("evaluate-uint16-ct", EVAL[:3] + ["{d}/ct_u16.nrrd"] + EVAL[4:], ["uint16"]),
    # --- phantom
    ("phantom-seed-negative", ["phantom", "cube", "--size", "small", "--seed", "-1", "-o",
                               "{o}/ph"], ["--seed", "≥ 0"]),
    ("phantom-unknown-name", ["phantom", "sphere-of-cheese", "-o", "{o}/ph"], ["invalid choice"]),
    ("phantom-output-is-input-folder", ["phantom", "cube", "--size", "small", "-o", "{d}"],
     ["holds files tetdose did not write", "--overwrite"]),
    # --- deform
    ("deform-duplicate-vertices", _with(DEFORM, mesh="{d}/duplicates.vtu"), ["coincide", "merge"]),
    ("deform-negative-density", _with(DEFORM, mesh="{d}/neg_density.vtu"),
     ["negative", "tetdose map"]),
    ("deform-nan-density", _with(DEFORM, mesh="{d}/nan_density.vtu"), ["NaN", "tetdose map"]),
    ("deform-unmapped-mesh", _with(DEFORM, mesh="{d}/mesh.vtu"), ["no point_data 'density'"]),
    ("deform-inverted-tets", _with(DEFORM, mesh="{d}/inverted_mapped.vtu"),
     ["inverted", "tetdose map --fix-orientation"]),
    ("deform-n-phases-zero", _with(DEFORM, **{"n-phases": "0"}), ["--n-phases", "≥ 1"]),
    ("deform-amplitude-nan", DEFORM + ["--amplitude-mm", "nan"], ["--amplitude-mm", "finite"]),
    ("deform-mismatched-phases", DEFORM[:4] + ["--phases", "{d}/phase_other.vtu"] + DEFORM[7:],
     ["topology", "phase 0"]),
    ("deform-dvf-is-a-ct", DEFORM[:4] + ["--dvf", "{d}/ct.nrrd"] + DEFORM[7:],
     ["DVF", "3 components"]),
    ("deform-4dct-without-reference", DEFORM[:4] + ["--4dct", "{d}/ct.nrrd", "{d}/ct.nrrd"]
     + DEFORM[7:], ["--reference"]),
    ("deform-output-holds-input", DEFORM[:4] + ["--phases", "{d}/phases/phase_001.vtu", "-o",
                                                "{d}/phases"], ["holds the input"]),
    # --- 4dct
    ("4dct-background-word", V4D + ["--background", "water"], ["--background", "ct, air"]),
    ("4dct-background-negative", V4D + ["--background", "-3"], ["--background", "≥ 0"]),
    ("4dct-output-is-phases", V4D[:-1] + ["{d}/phases"], ["also an input"]),
    ("4dct-mismatched-phases", _with(V4D, phases="{d}/phases_mixed"), ["topology", "phase 1"]),
    ("4dct-like-uint16", _with(V4D, like="{d}/ct_u16.nrrd"), ["uint16", "signed HU"]),
    ("4dct-like-sheared", _with(V4D, like="{d}/dicom_sheared"), ["gantry tilt",
                                                                 "--resample-tilted"]),
    ("4dct-like-mr", _with(V4D, like="{d}/dicom_mr"), ["modality", "CT series"]),
    ("4dct-missing-phases", _with(V4D, phases="{d}/nope"), ["does not exist"]),
    # --- dose
    ("dose-histories-nan", _with(DOSE, histories="nan"), ["--histories", "whole number"]),
    ("dose-histories-inf", _with(DOSE, histories="inf"), ["--histories", "whole number"]),
    ("dose-histories-negative", _with(DOSE, histories="-5"), ["--histories", "whole number"]),
    ("dose-histories-1e15", _with(DOSE, histories="1e15"), ["would take about", "--histories"]),
    ("dose-batches-zero", DOSE + ["--batches", "0"], ["--batches", "≥ 2"]),
    ("dose-cutoff-negative", DOSE + ["--cutoff-mev", "-1"], ["--cutoff-mev"]),
    ("dose-seed-negative", DOSE + ["--seed", "-1"], ["--seed", "≥ 0"]),
    ("dose-duplicate-vertices", _with(DOSE, mesh="{d}/duplicates.vtu"), ["coincide", "merge"]),
    ("dose-negative-density", _with(DOSE, mesh="{d}/neg_density.vtu"), ["negative"]),
    ("dose-nan-density", _with(DOSE, mesh="{d}/nan_density.vtu"), ["NaN", "tetdose map"]),
    ("dose-unmapped-mesh", _with(DOSE, mesh="{d}/mesh.vtu"), ["no point_data 'density'"]),
    ("dose-inverted-tets", _with(DOSE, mesh="{d}/inverted_mapped.vtu"),
     ["inverted", "tetdose map --fix-orientation"]),
    ("dose-unknown-plan-key", _with(DOSE, plan="{d}/plan_unknown_key.toml"),
     ["unknown", "colour"]),
    ("dose-position-word", _with(DOSE, plan="{d}/plan_position_word.toml"), ["position_mm"]),
    ("dose-energy-too-high", _with(DOSE, plan="{d}/plan_energy_high.toml"), ["energies", "MeV"]),
    ("dose-energy-negative", _with(DOSE, plan="{d}/plan_energy_negative.toml"),
     ["energies", "MeV"]),
    ("dose-beam-misses", _with(DOSE, plan="{d}/plan_miss.toml"), ["miss", "position_mm"]),
    ("dose-unknown-extension", DOSE[:-1] + ["{o}/dose.xyz"], ["dose.xyz", ".vtu"]),
    ("dose-output-is-input", DOSE[:-1] + ["{d}/mapped.vtu"], ["also an input"]),
    ("dose-ct-uint16", DOSE_CT[:2] + ["{d}/ct_u16.nrrd"] + DOSE_CT[3:], ["uint16"]),
    ("dose-ct-sheared", DOSE_CT[:2] + ["{d}/dicom_sheared"] + DOSE_CT[3:], ["gantry tilt"]),
    ("dose-ct-4d", DOSE_CT[:2] + ["{d}/ct_4d.nrrd"] + DOSE_CT[3:], ["3-D image", "4-D"]),
    ("dose-bad-calibration", DOSE_CT + ["--calibration", "{d}/bad_cal.csv"], ["increasing"]),
    # --- dose4d
    ("dose4d-mismatched-phases", _with(DOSE4D, phases="{d}/phases_mixed"), ["topology"]),
    ("dose4d-histories-nan", _with(DOSE4D, histories="nan"), ["--histories", "whole number"]),
    ("dose4d-output-is-phases", DOSE4D[:-1] + ["{d}/phases"], ["also an input"]),
    ("dose4d-like-uint16", DOSE4D + ["--like", "{d}/ct_u16.nrrd"], ["uint16"]),
    ("dose4d-beam-misses", _with(DOSE4D, plan="{d}/plan_miss.toml"), ["miss"]),
    # --- compare and export-dose
    ("compare-all-zero-dose", CMP[:3] + ["{d}/zero_dose.vtu", "--voxel-dose",
                                         "{d}/zero_dose.nrrd"] + CMP[6:], ["zero", "dose"]),
    ("compare-threshold-150", CMP + ["--threshold", "150"], ["--threshold", "100"]),
    ("compare-threshold-negative", CMP + ["--threshold", "-5"], ["--threshold"]),
    ("compare-threshold-100", CMP + ["--threshold", "100"], ["--threshold", "[0, 100)"]),
    ("compare-gamma-points-zero", CMP + ["--gamma-max-points", "0"], ["--gamma-max-points"]),
    ("compare-mesh-without-dose", _with(CMP, **{"mesh-dose": "{d}/mapped.vtu"}),
     ["cell_data 'dose'"]),
    ("export-unknown-extension", EXPORT[:-1] + ["{o}/rd.xyz"], ["rd.xyz", ".dcm"]),
    # --- mesh
    ("mesh-labels-is-a-ct", ["mesh", "--labels", "{d}/ct.nrrd", "-o", "{o}/m.vtu"],
     ["--labels", "CT"]),
    ("mesh-size-negative", ["mesh", "--labels", "{d}/labels.nrrd", "--size-mm", "-3", "-o",
                            "{o}/m.vtu"], ["--size-mm", "> 0"]),
    ("mesh-unknown-extension", ["mesh", "--labels", "{d}/labels.nrrd", "-o", "{o}/m.xyz"],
     ["unknown extension"]),
    ("mesh-no-input", ["mesh", "-o", "{o}/m.vtu"], ["--labels"]),
    # --- register
    ("register-reference-absent", _with(REG, reference="37"), ["37 %", "pick one"]),
    ("register-phase-uint16", REG[:3] + ["{d}/ct_u16.nrrd"] + REG[4:], ["uint16"]),
    ("register-smoothing-negative", REG + ["--smoothing-mm", "-1"], ["--smoothing-mm"]),
    ("register-threads-zero", REG + ["--threads", "0"], ["--threads", "≥ 1"]),
    ("register-output-is-input", REG[:-1] + ["{d}"], ["holds the input"]),
    # --- issue 23: one patient, one frame (checked before any work)
    ("dose-rtplan-other-patient", _with(DOSE_RT, rtplan="{d}/rtplan_other_patient.dcm"),
     ["PatientID differs", "SOMEONE-ELSE", "RT Plan", "--allow-frame-mismatch"]),
    ("dose-rtplan-other-frame", _with(DOSE_RT, rtplan="{d}/rtplan_other_frame.dcm"),
     ["FrameOfReferenceUID differs", "1.2.826.0.1.3680043.8.498.999", "--allow-frame-mismatch"]),
    ("mesh-rtstruct-other-frame", _with(MESH_RS, structures="{d}/rs_other_frame.dcm"),
     ["FrameOfReferenceUID differs", "RT Structure Set", "--allow-frame-mismatch"]),
    ("register-4dct-two-patients", _with(REG, **{"4dct": "{d}/ct4d_mixed"})[:4] + REG[5:],
     ["PatientID differs", "SOMEONE-ELSE", "4D-CT 50%", "--allow-frame-mismatch"]),
    ("dose4d-ct4d-two-studies", DOSE4D + ["--ct4d", "{d}/ct4d_two_studies"],
     ["StudyInstanceUID differs", "one study", "--allow-frame-mismatch"]),
    # --- units and placement of a mesh
    ("map-mesh-in-metres", _map(mesh="{d}/mapped_in_m.vtu"), ["metres", "--mesh-unit m"]),
    ("voxelize-mesh-in-metres", _with(VOX, mesh="{d}/mapped_in_m.vtu"),
     ["one voxel", "metres", "--mesh-unit m"]),
    ("dose-hybrid-mesh-in-metres", _with(HYBRID, mesh="{d}/mapped_in_m.vtu"),
     ["metres", "--mesh-unit m"]),
    ("dose-hybrid-mesh-20x", _with(HYBRID, mesh="{d}/mapped_x20.vtu"), ["15×", "not in mm"]),
    ("map-mesh-unit-wrong", _map(mesh="{d}/mapped.vtu") + ["--mesh-unit", "m"],
     ["read as m", "not in mm"]),
    # --- label images: whole numbers only, everywhere
    ("dose-labels-fractional", DOSE_CT + ["--labels", "{d}/labels_linear.nrrd"],
     ["non-integer", "0.5", "nearest-neighbour"]),
    ("mesh-labels-fractional", _with(MESH, labels="{d}/labels_linear.nrrd"),
     ["non-integer", "nearest-neighbour"]),
    ("compare-structures-fractional", CMP + ["--structures", "{d}/labels_linear.nrrd"],
     ["non-integer", "nearest-neighbour"]),
    # --- bounded meshing
    ("mesh-one-voxel-label", _with(MESH, labels="{d}/labels_one_voxel.nrrd"),
     ["label 2 has 1 voxel", "too small", "--label"]),
    ("mesh-size-unbounded", MESH + ["--size-mm", "0.1"], ["GB of memory", "--force"]),
    ("mesh-over-time-limit", MESH + ["--max-minutes", "0.001"], ["--max-minutes", "--force"]),
    ("mesh-two-rois-one-name", _with(MESH_RS, structures="{d}/rs_two_gtv.dcm"),
     ["2 ROIs named 'GTV'", "--roi 'GTV (2)'"]),
    ("demo-size-unreadable", ["demo", "--size-mm", "tumour", "-o", "{o}/demo"],
     ["--size-mm", "cannot read 'tumour'", "tumour=14"]),
    # --- outputs: checked before any work, never inside an input folder
    ("export-dose-into-ct-series", _with(EXPORT, like="{d}/dicom_ok")[:-1]
     + ["{d}/dicom_ok/rd.dcm"], ["inside the input folder", "DICOM series"]),
    ("dose-image-beside-is-input", HYBRID[:-3] + ["{d}/ct.vtu"] + HYBRID[-2:],
     ["also writes ct.nrrd beside it", "also an input"]),
    ("dose-nested-output-folders", _with(DOSE, mesh="{d}/inverted_mapped.vtu")[:-1]
     + ["{o}/new/deeper/dose.vtu"], ["inverted"]),
    ("map-ct-folder-without-dicom", _map(ct="{d}/not_dicom"), ["holds no DICOM image series"]),
    # --- honest messages
    ("dose-prescription-too-few-histories", _with(DOSE_CT, plan="{d}/plan_rx.toml",
                                                  histories="30")
     + ["--labels", "{d}/labels.nrrd", "-q"],
     ["too few histories", "% of the structure 'tissue' scored nothing", "raise --histories"]),
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
    """Every folder-writing command given an existing file for -o: one line, the file kept."""
    blocker = tmp_path / "taken"
    blocker.write_bytes(b"precious")
    for base in (EVAL, DEFORM, V4D, DOSE4D, CMP, ["phantom", "cube", "--size", "small", "-o", ""]):
        argv = base[:-1] + [str(blocker)]
        code = main([a.format(d=d, o=tmp_path) for a in argv])
        err = capsys.readouterr().err.strip()
        assert code == 2 and len(err.splitlines()) == 1 and "existing file" in err, err
        assert blocker.read_bytes() == b"precious"


@pytest.mark.parametrize("base", [["phantom", "cube", "--size", "small", "-o", "."],
                                  DOSE4D[:-1] + ["."], DEFORM[:-1] + ["."]],
                         ids=["phantom", "dose4d", "deform"])
def test_current_folder_as_output_is_refused(d, tmp_path, capsys, monkeypatch, base):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "keep.txt").write_text("mine")
    assert main([a.format(d=d) for a in base]) == 2
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


@pytest.mark.parametrize("argv", [MAP, DOSE, DEFORM, V4D, DOSE4D, CMP, EXPORT],
                         ids=lambda argv: argv[0])
def test_unwritable_output_folder_is_one_line(d, tmp_path, capsys, monkeypatch, argv):
    """A read-only folder (simulated: the tests may run as root, who may write anywhere)."""
    real_access = os.access
    monkeypatch.setattr(os, "access", lambda p, mode, **kw: False if Path(p) == tmp_path
                        else real_access(p, mode, **kw))
    code = main([a.format(d=d, o=tmp_path) for a in argv])
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


def test_tilted_series_is_resampled_on_request(d, tmp_path, capsys):
    """The refused sheared series maps with --resample-tilted, and the warning says so."""
    argv = [a.format(d=d, o=tmp_path) for a in _map(ct="{d}/dicom_sheared")]
    with pytest.warns(UserWarning, match="resampled onto an orthogonal grid"):
        assert main([*argv, "--resample-tilted"]) == 0
    assert (tmp_path / "out.vtu").exists()
