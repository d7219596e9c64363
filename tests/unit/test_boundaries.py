"""Trust at the boundaries (issue 23): allowed mismatches recorded, mesh units, label images,
outputs as one atomic set, honest prescription messages, ITK messages captured, meshing bounded.

The refusals themselves are rows of the CLI error table (test_cli_errors.py); here: what each
rule accepts, what an allowed mismatch leaves in the records, and the rules' own arithmetic.
"""

from __future__ import annotations

import errno
import json
import os
import warnings
from pathlib import Path

import numpy as np
import pytest

from cli_inputs import build
from tetdose._atomic import atomic_outputs, atomic_write_file, output_policy, record_note
from tetdose.cli import main
from tetdose.core.image import Image, ImageGrid
from tetdose.core.io import check_labels, mesh_unit_policy, read_mesh
from tetdose.core.units import check_mesh_on_grid
from tetdose.dicom.identity import NOTE_KEY, check_inputs, frame_policy, identities_of
from tetdose.errors import GeometryMismatchError, ImageError, MeshError, PlanError
from tetdose.plan.prescription import Prescription, scale_for


@pytest.fixture(scope="module")
def d(tmp_path_factory) -> Path:
    return build(tmp_path_factory.mktemp("inputs"))


# --- one patient, one frame -------------------------------------------------------------------

def test_identities_of_files_and_folders(d):
    (ct,) = identities_of(d / "dicom_ok")
    (plan,) = identities_of(d / "rtplan.dcm")
    (rs,) = identities_of(d / "rs.dcm")
    assert ct.modality == "CT" and plan.modality == "RTPLAN" and rs.modality == "RTSTRUCT"
    assert ct.patient_id == plan.patient_id == rs.patient_id == "TETDOSE-ANON"
    assert ct.frame_uid == plan.frame_uid == rs.frame_uid != ""  # RTSTRUCT: referenced frame
    assert len(identities_of(d / "ct4d_mixed")) == 2
    assert identities_of(d / "ct.nrrd") == [] and identities_of(d / "phases") == []
    assert check_inputs([d / "dicom_ok", d / "rtplan.dcm", d / "rs.dcm", d / "ct.nrrd"]) == []


def test_a_mismatch_allowed_warns_once_and_is_recorded_in_every_json(d, tmp_path, capsys):
    argv = ["dose", "-q", "--ct", str(d / "dicom_ok"), "--rtplan",
            str(d / "rtplan_other_patient.dcm"), "--histories", "2000", "--batches", "2",
            "-o", str(tmp_path / "dose.nrrd")]
    with pytest.warns(UserWarning, match="PatientID differs.*allowed"):
        assert main([*argv, "--allow-frame-mismatch"]) == 0
    record = json.loads((tmp_path / "dose.json").read_text())
    (note,) = record[NOTE_KEY]
    assert "'TETDOSE-ANON'" in note and "'SOMEONE-ELSE'" in note
    # the same inputs of one patient: no note
    assert main([*argv[:5], str(d / "rtplan.dcm"), *argv[6:-1], str(tmp_path / "ok.nrrd")]) == 0
    assert NOTE_KEY not in json.loads((tmp_path / "ok.json").read_text())


def test_read_4dct_refuses_two_patients_unless_allowed(d):
    from tetdose.motion.ct4d_read import read_4dct

    with pytest.raises(GeometryMismatchError, match="PatientID differs.*SOMEONE-ELSE"):
        read_4dct(d / "ct4d_mixed")
    with frame_policy(True), pytest.warns(UserWarning, match="allowed"):
        assert [p.percent for p in read_4dct(d / "ct4d_mixed")] == [0.0, 50.0]


# --- units and placement of a mesh --------------------------------------------------------------

GRID = ImageGrid((-250.0, -250.0, -100.0), (2.0, 2.0, 5.0), np.eye(3), (250, 250, 40))


def _cube(centre, side):
    corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float)
    return np.asarray(centre, float) + (corners - 0.5) * side


@pytest.mark.parametrize(("unit", "scale"), [("m", 1e-3), ("cm", 0.1)])
def test_a_lung_in_m_or_cm_is_refused_with_its_unit(unit, scale):
    lung = _cube((60.0, -20.0, 0.0), 150.0) * scale  # 15 cm across, in metres or cm
    with pytest.raises(GeometryMismatchError, match=f"--mesh-unit {unit}"):
        check_mesh_on_grid(lung, (150.0 * scale) ** 3, GRID)
    check_mesh_on_grid(lung / scale, 150.0**3, GRID)  # the same lung in mm passes


def test_a_small_structure_in_mm_passes_unless_it_could_be_cm():
    far = _cube((60.0, -20.0, 80.0), 30.0)  # 3 cm tumour: ×10 lies outside the CT
    check_mesh_on_grid(far, 30.0**3, GRID)
    near = _cube((2.0, 1.0, 0.5), 15.0)  # at the origin: ×10 would still fit, so it asks
    with pytest.raises(GeometryMismatchError, match="--mesh-unit mm if it really is"):
        check_mesh_on_grid(near, 15.0**3, GRID)
    check_mesh_on_grid(near, 15.0**3, GRID, unit="mm")  # said so: accepted


def test_mesh_ten_times_larger_and_wholly_outside():
    with pytest.raises(GeometryMismatchError, match=r"12× the 500 mm"):
        check_mesh_on_grid(_cube((0, 0, 0), 6000.0), 6000.0**3, GRID)
    low = ImageGrid((-250.0, -250.0, -600.0), (2.0, 2.0, 5.0), np.eye(3), (250, 250, 40))
    lung_cm = _cube((60.0, -20.0, -500.0), 150.0) / 10.0  # off the CT, which starts at -600 mm
    with pytest.raises(GeometryMismatchError, match="wholly outside.*--mesh-unit cm"):
        check_mesh_on_grid(lung_cm, 15.0**3, low)


def test_a_stated_unit_that_puts_the_mesh_off_the_image_is_questioned():
    """Issue 27: a mm liver given --mesh-unit cm (10× too large, mostly off the CT) was mapped
    against a fraction of its CT mass with only "extend the image"."""
    liver_mm = _cube((60.0, -20.0, 0.0), 150.0)
    with pytest.raises(GeometryMismatchError, match=r"read in cm .*outside the image, while "
                       r"read in mm it lies inside.*--mesh-unit mm"):
        check_mesh_on_grid(liver_mm * 10.0, 1500.0**3, GRID, unit="cm")
    check_mesh_on_grid(liver_mm, 150.0**3, GRID, unit="mm")  # the right unit passes
    # a cm mesh off a cropped CT stays accepted: read in mm it would be a speck
    beyond = _cube((0.0, 0.0, 20.0), 20.0) * 10.0
    check_mesh_on_grid(beyond, 200.0**3, GRID, unit="cm")


def test_mesh_unit_m_reads_the_metre_mesh_as_the_mm_one(d, tmp_path):
    mm = read_mesh(d / "mapped.vtu")
    with mesh_unit_policy("m"):
        m = read_mesh(d / "mapped_in_m.vtu")
    np.testing.assert_allclose(m.points_mm, mm.points_mm, rtol=1e-12)
    argv = ["map", "-q", "--ct", str(d / "ct.nrrd"), "--mesh", str(d / "mapped_in_m.vtu")]
    assert main([*argv, "--mesh-unit", "m", "-o", str(tmp_path / "m.vtu")]) == 0
    np.testing.assert_allclose(read_mesh(tmp_path / "m.vtu").points_mm, mm.points_mm,
                               rtol=1e-12)
    assert main(["dose", "-q", "--mesh", str(d / "mapped_in_m.vtu"), "--ct", str(d / "ct.nrrd"),
                 "--plan", str(d / "plan.toml"), "--histories", "2000", "--batches", "2",
                 "--mesh-unit", "m", "-o", str(tmp_path / "dose.vtu")]) == 0
    assert json.loads((tmp_path / "dose.json").read_text())["mesh_unit"] == "m"


# --- label images: one rule ----------------------------------------------------------------------

def test_label_rule():
    g = ImageGrid(np.zeros(3), np.ones(3), np.eye(3), (3, 2, 1))
    ok = check_labels(Image(np.array([[[0.0, 1.0, 2.0], [3.0, 0.0, 1.0]]]), g))
    assert ok.array.dtype == np.int64 and ok.array.max() == 3
    with pytest.raises(ImageError, match=r"non-integer.*1\.5 at i=1, j=1, k=0.*nearest"):
        check_labels(Image(np.array([[[0.0, 1.0, 2.0], [3.0, 1.5, 1.0]]]), g))
    with pytest.raises(ImageError, match="non-integer"):
        check_labels(Image(np.array([[[0.0, np.nan, 2.0], [3.0, 0.0, 1.0]]]), g))


# --- outputs ------------------------------------------------------------------------------------

def test_outputs_of_one_command_are_one_set(tmp_path):
    with pytest.raises(RuntimeError, match="while writing"), atomic_outputs():
        with atomic_write_file(tmp_path / "a" / "first.txt") as tmp:
            tmp.write_text("one")
        assert not (tmp_path / "a" / "first.txt").exists()  # staged, not yet in place
        with atomic_write_file(tmp_path / "a" / "second.txt") as tmp:
            raise RuntimeError("the disk filled while writing the second file")
    assert list(tmp_path.iterdir()) == [], "a partial set, a temporary or a folder was left"
    with atomic_outputs():
        for name in ("x.txt", "y.txt"):
            with atomic_write_file(tmp_path / "b" / name) as tmp:
                tmp.write_text(name)
    assert sorted(p.name for p in (tmp_path / "b").iterdir()) == ["x.txt", "y.txt"]


def test_record_notes_go_into_json_records_but_not_figure_data(tmp_path):
    with output_policy():
        record_note("note", ["said"])
        for name in ("run.json", "figures.json"):
            with atomic_write_file(tmp_path / name) as tmp:
                tmp.write_text(json.dumps({"a": 1}))
    assert json.loads((tmp_path / "run.json").read_text()) == {"a": 1, "note": ["said"]}
    assert json.loads((tmp_path / "figures.json").read_text()) == {"a": 1}


def _mount_tmpfs(path: Path, size: str) -> bool:
    import subprocess

    path.mkdir()
    try:
        done = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)],
                              capture_output=True, timeout=20)
    except (OSError, subprocess.SubprocessError):
        return False
    return done.returncode == 0


def test_disk_full_on_the_second_file_leaves_no_partial_set(d, tmp_path, capsys):
    """A real full disk (a small tmpfs; skipped where it cannot be mounted): the hybrid dose
    writes dose.vtu, then its images — full on the images, no file of the set is kept."""
    import subprocess

    argv = ["dose", "-q", "--mesh", str(d / "mapped.vtu"), "--ct", str(d / "ct.nrrd"), "--plan",
            str(d / "plan.toml"), "--histories", "2000", "--batches", "2"]
    assert main([*argv, "-o", str(tmp_path / "ref" / "dose.vtu")]) == 0
    sizes = {p.name: p.stat().st_size for p in (tmp_path / "ref").iterdir()}
    disk = tmp_path / "disk"
    if not _mount_tmpfs(disk, "1m"):
        pytest.skip("cannot mount a tmpfs here (needs root and mount permission)")
    try:
        # fill the disk so that dose.vtu fits but not the images after it (tmpfs counts pages)
        st = os.statvfs(disk)
        page = st.f_frsize
        pages = {name: -(-size // page) for name, size in sizes.items()}
        room = pages["dose.vtu"] * page
        (disk / "filler").write_bytes(b"\0" * (st.f_bavail * page - room))
        assert pages["dose.vtu"] + pages["dose.nrrd"] > room // page
        code = main([*argv, "-o", str(disk / "out" / "dose.vtu")])
        err = capsys.readouterr().err.strip()
        assert code == 2 and len(err.splitlines()) == 1 and "no space left" in err, err
        assert sorted(p.name for p in disk.iterdir()) == ["filler"]  # no partial set, no folder
    finally:
        subprocess.run(["umount", str(disk)], capture_output=True, timeout=20)


def test_an_error_leaves_no_folder_it_created(d, tmp_path, monkeypatch, capsys):
    import meshio

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(meshio, "write", full)
    assert main(["map", "-q", "--ct", str(d / "ct.nrrd"), "--mesh", str(d / "mesh.vtu"), "-o",
                 str(tmp_path / "new" / "deeper" / "m.vtu")]) == 2
    assert "no space left" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


# --- honest prescription messages ----------------------------------------------------------------

def test_prescription_messages_say_what_happened():
    rx = Prescription("tumour", 2.0, "D95")
    mass, mask = np.ones(10), np.arange(10) < 6
    with pytest.raises(PlanError, match="scored no dose at all"):
        scale_for(rx, np.r_[np.zeros(6), np.ones(4)], mass, mask)
    with pytest.raises(PlanError, match=r"too few histories: 33 % of the structure"):
        scale_for(rx, np.r_[0, 0, 1, 1, 1, 1, np.ones(4)], np.ones(10), mask)
    dose = np.r_[np.ones(6), 20.0, 1, 1, 1]  # scaled: the hot cell gets 40 Gy = 20× 2 Gy
    with pytest.warns(UserWarning, match=r"near-maximum dose \(D0.1\) at 40 Gy per fraction, 20×"):
        assert scale_for(rx, dose, mass, mask) == pytest.approx(2.0)
    tiny = np.r_[np.ones(9), 1e-5]  # a noise spike in a cell of 1e-6 of the mass is no maximum
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scale_for(rx, np.r_[np.ones(9), 20.0], tiny, mask)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scale_for(rx, np.r_[np.ones(6), 4.0, 1, 1, 1], mass, mask)  # 4× is no warning


# --- ITK messages --------------------------------------------------------------------------------

def test_itk_messages_never_reach_the_terminal(d, tmp_path, capfd):
    assert main(["map", "-q", "--ct", str(d / "not_dicom"), "--mesh", str(d / "mesh.vtu"),
                 "-o", str(tmp_path / "m.vtu")]) == 2
    err = capfd.readouterr().err
    assert "WARNING: In" not in err and ".cxx" not in err, err
    assert err.strip().splitlines() == [err.strip()] and "holds no DICOM image series" in err


def test_itk_warnings_of_a_successful_read_become_tetdose_warnings():
    import SimpleITK as sitk

    from tetdose.core.io import itk_messages

    with pytest.warns(UserWarning, match=r"^what: SimpleITK reported: .*not a directory") as rec, \
            itk_messages("what"):
        sitk.ImageSeriesReader.GetGDCMSeriesFileNames("/nonexistent-folder-for-itk", "1.2.3")
    assert all(".cxx" not in str(w.message) for w in rec)


# --- bounded meshing ------------------------------------------------------------------------------

def test_face_areas_and_the_estimate_grow_as_the_size_shrinks():
    from tetdose.meshing.mmg import estimate, face_areas_mm2

    arr = np.zeros((4, 5, 6), np.int64)
    arr[1:3, 1:4, 1:5] = 2
    # faces normal to x: dy·dz = 2·3 mm² × (2·3 rows × 2 sides); to y: 1·3 × 16; to z: 1·2 × 24
    assert face_areas_mm2(arr, [2], np.array([1.0, 2.0, 3.0])) == {(0, 2): 72.0 + 48.0 + 48.0}
    small, large = (estimate({1: 1e6}, {1: h}, {(0, 1): 6e4}) for h in (2.0, 8.0))
    assert small.n_tets > 16 * large.n_tets and small.memory_bytes > large.memory_bytes


def test_a_label_too_small_to_mesh_is_named_before_mmg():
    pytest.importorskip("mmgpy")
    from tetdose.meshing import conforming_mesh

    g = ImageGrid(np.zeros(3), np.full(3, 2.0), np.eye(3), (20, 20, 20))
    arr = np.zeros(g.shape, np.int16)
    arr[4:16, 4:16, 4:16] = 1
    arr[2, 2, 2] = 7
    with pytest.raises(MeshError, match=r"label 7 has 1 voxel \(8 mm³\): too small"):
        conforming_mesh(Image(arr, g))


def test_a_crashed_mesher_is_one_clear_error(tmp_path):
    from tetdose.meshing.worker import _outcome

    class Dead:
        returncode = -11

    log = tmp_path / "output.log"
    log.write_text("  MMG3DLIB: start\n  ## Error: unable to allocate the mesh.\n")
    with pytest.raises(MeshError, match=r"died \(signal 11 \(SIGSEGV\)\); its last words: ## "
                                        r"Error: unable to allocate.*--size-mm"):
        _outcome(Dead(), tmp_path / "no-result.pickle", log)
