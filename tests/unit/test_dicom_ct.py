"""DICOM CT series writer: validity (dciodvfy/dcentvfy), geometry and HU read back by
independent readers (SimpleITK/GDCM, pydicom), 4D-CT UIDs, reference copy, determinism, atomicity.
"""

from __future__ import annotations

import shutil
import subprocess
import warnings
from pathlib import Path

import numpy as np
import pydicom
import pytest
import SimpleITK as sitk

import tetdose.dicom.ct_series as ct_series
from tetdose.core.image import Image, ImageGrid
from tetdose.dicom import write_ct_series, write_ct_series_4d
from tetdose.errors import DicomError

SHARED = Path(__file__).resolve().parents[2] / ".." / "shared"
ABDOMEN = SHARED / "data" / "abdomen-dicom" / "series"


def rotation(ax: float, ay: float, az: float) -> np.ndarray:
    """Rz·Ry·Rx for angles in degrees (an oblique, right-handed direction)."""
    cx, cy, cz = np.cos(np.radians([ax, ay, az]))
    sx, sy, sz = np.sin(np.radians([ax, ay, az]))
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return rz @ ry @ rx


DIRECTIONS = {
    "identity": np.eye(3),
    "oblique": rotation(20.0, -35.0, 50.0),
    "y_flipped": np.diag([1.0, -1.0, 1.0]),
}


def make_ct(direction=None, seed: int = 0, size=(7, 5, 4), lo=-1000.0, hi=2000.0) -> Image:
    grid = ImageGrid(
        (-12.5, 40.0, -300.0), (0.8, 1.25, 2.5), np.eye(3) if direction is None else direction, size
    )
    hu = np.random.default_rng(seed).uniform(lo, hi, grid.shape)
    return Image(hu, grid)


def tool_lines(tool: str, *paths: Path) -> list[str]:
    """Output lines of a dicom3tools validator (skips the test when it is not installed)."""
    if shutil.which(tool) is None:
        pytest.skip(f"{tool} (Debian package dicom3tools) is not installed")
    run = subprocess.run([tool, *map(str, paths)], capture_output=True, text=True, check=False)
    return (run.stdout + run.stderr).splitlines()


def errors_of(tool: str, *paths: Path) -> list[str]:
    return [line for line in tool_lines(tool, *paths) if "Error" in line]


def read_series(folder: Path) -> sitk.Image:
    reader = sitk.ImageSeriesReader()
    reader.SetFileNames(reader.GetGDCMSeriesFileNames(str(folder)))
    return reader.Execute()


def assert_same_voxels(read: Image, written: Image, tol: float) -> None:
    """Every read voxel sits on a written voxel centre and carries its value (within tol)."""
    np.testing.assert_allclose(read.grid.spacing_mm, written.grid.spacing_mm, atol=1e-6)
    assert read.grid.size == written.grid.size
    index = written.grid.physical_to_index(read.grid.voxel_centers_mm())
    np.testing.assert_allclose(index, np.rint(index), atol=1e-5)
    i, j, k = np.rint(index).astype(int).T
    expected = written.array[k, j, i]
    np.testing.assert_allclose(read.array.ravel(), expected, atol=tol, rtol=0)


@pytest.mark.parametrize("name", DIRECTIONS)
def test_every_file_passes_dciodvfy_and_series_passes_dcentvfy(tmp_path, name):
    files = write_ct_series(make_ct(DIRECTIONS[name]), tmp_path / "ct")
    assert len(files) == 4
    for f in files:
        assert errors_of("dciodvfy", f) == [], f
    assert errors_of("dcentvfy", *files) == []


@pytest.mark.parametrize("name", DIRECTIONS)
def test_simpleitk_reads_same_geometry_and_hu(tmp_path, name):
    image = make_ct(DIRECTIONS[name])
    write_ct_series(image, tmp_path / "ct")
    read = Image.from_sitk(read_series(tmp_path / "ct"))
    assert_same_voxels(read, image, tol=0.5 + 1e-9)
    if np.linalg.det(image.grid.direction) > 0:
        np.testing.assert_allclose(read.grid.origin_mm, image.grid.origin_mm, atol=1e-5)
        np.testing.assert_allclose(read.grid.direction, image.grid.direction, atol=1e-6)
    else:
        # GDCM stacks slices along row × column: the right-handed twin of a y-flipped grid.
        last = image.grid.index_to_physical(np.array([0.0, 0.0, image.grid.size[2] - 1]))
        np.testing.assert_allclose(read.grid.origin_mm, last, atol=1e-5)
        np.testing.assert_allclose(read.grid.direction[:, :2], image.grid.direction[:, :2])


def test_pydicom_attributes_per_slice(tmp_path):
    image = make_ct(DIRECTIONS["oblique"])
    files = write_ct_series(image, tmp_path / "ct", series_number=7, series_description="vct")
    grid = image.grid
    for k, f in enumerate(files):
        ds = pydicom.dcmread(f)
        assert ds.file_meta.TransferSyntaxUID == pydicom.uid.ExplicitVRLittleEndian
        assert ds.SOPClassUID == pydicom.uid.CTImageStorage
        assert (ds.Rows, ds.Columns) == (grid.size[1], grid.size[0])
        np.testing.assert_allclose(ds.PixelSpacing, [1.25, 0.8])
        np.testing.assert_allclose(ds.SliceThickness, 2.5)
        np.testing.assert_allclose(ds.SpacingBetweenSlices, 2.5)
        np.testing.assert_allclose(ds.ImageOrientationPatient, grid.direction[:, :2].T.ravel())
        expected_ipp = grid.origin_mm + grid.direction[:, 2] * 2.5 * k
        np.testing.assert_allclose(ds.ImagePositionPatient, expected_ipp, atol=1e-9)
        assert ds.InstanceNumber == k + 1 and ds.SeriesNumber == 7
        assert ds.SeriesDescription == "vct" and ds.Modality == "CT"
        assert ds.pixel_array.dtype == np.int16 and ds.RescaleSlope == 1
        hu = ds.pixel_array * float(ds.RescaleSlope) + float(ds.RescaleIntercept)
        np.testing.assert_allclose(hu, image.array[k], atol=0.5 + 1e-9)
        for keyword in ("PatientName", "PatientID", "PatientBirthDate", "PatientSex", "StudyDate",
                        "StudyTime", "ReferringPhysicianName", "StudyID", "AccessionNumber",
                        "PositionReferenceIndicator", "PatientPosition", "KVP",
                        "AcquisitionNumber"):  # fmt: skip
            assert keyword in ds, keyword  # Type 2: present, possibly empty


def test_hu_beyond_int16_uses_intercept_then_clips_with_warning():
    hu_int = np.array([[[-1024, 0, 3071]]], dtype=np.int16)
    stored, intercept = ct_series.hu_to_stored(hu_int)
    assert intercept == 0 and stored.dtype == np.int16
    np.testing.assert_array_equal(stored, hu_int)
    stored, intercept = ct_series.hu_to_stored(np.array([-1000.4, 40000.2, 12.0]))
    assert stored.dtype == np.int16 and intercept != 0
    np.testing.assert_array_equal(stored.astype(np.int64) + intercept, [-1000, 40000, 12])
    with pytest.warns(UserWarning, match="clipped"):
        stored, intercept = ct_series.hu_to_stored(np.array([-40000.0, 40000.0]))
    assert stored.astype(np.int64)[0] + intercept == -40000
    assert stored.astype(np.int64)[1] + intercept == -40000 + 65535


def test_4d_series_share_study_and_frame_with_temporal_attributes(tmp_path):
    phases = [make_ct(seed=s) for s in range(3)]
    folders = write_ct_series_4d(phases, tmp_path / "ct4d", phase_percent=[0, 20, 50])
    assert [f.name for f in folders] == ["phase_000", "phase_020", "phase_050"]
    headers = [[pydicom.dcmread(f) for f in sorted(folder.iterdir())] for folder in folders]
    study = {ds.StudyInstanceUID for series in headers for ds in series}
    frame = {ds.FrameOfReferenceUID for series in headers for ds in series}
    assert len(study) == 1 and len(frame) == 1
    assert len({series[0].SeriesInstanceUID for series in headers}) == 3
    for i, series in enumerate(headers):
        assert len({ds.SeriesInstanceUID for ds in series}) == 1
        ds = series[0]
        assert ds.SeriesDescription == f"4D-CT {[0, 20, 50][i]}%"
        assert ds.TemporalPositionIdentifier == i + 1 and ds.NumberOfTemporalPositions == 3
        read = Image.from_sitk(read_series(folders[i]))
        assert_same_voxels(read, phases[i], tol=0.5 + 1e-9)
    sops = [ds.SOPInstanceUID for series in headers for ds in series]
    assert len(set(sops)) == len(sops)
    all_files = sorted(tmp_path.glob("ct4d/*/*.dcm"))
    assert errors_of("dciodvfy", all_files[0]) == []
    assert errors_of("dcentvfy", *all_files) == []


@pytest.mark.skipif(not ABDOMEN.is_dir(), reason=f"shared reference CT {ABDOMEN} is absent")
def test_reference_patient_and_study_are_copied(tmp_path):
    ref = pydicom.dcmread(sorted(ABDOMEN.iterdir())[0], stop_before_pixels=True)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        files = write_ct_series(make_ct(), tmp_path / "ct", reference=ABDOMEN)
    ds = pydicom.dcmread(files[0])
    for keyword in ("PatientName", "PatientID", "PatientBirthDate", "PatientSex", "StudyDate",
                    "StudyTime", "AccessionNumber", "ReferringPhysicianName", "StudyID",
                    "FrameOfReferenceUID", "PatientPosition"):  # fmt: skip
        assert ds[keyword].value == ref[keyword].value, keyword
    if ref.get("StudyInstanceUID"):
        assert ds.StudyInstanceUID == ref.StudyInstanceUID
    else:  # the shared series is anonymised: a stable derived UID, with a warning
        assert any("Study Instance UID" in str(w.message) for w in caught)
        assert pydicom.uid.UID(ds.StudyInstanceUID).is_valid
        with pytest.warns(UserWarning, match="Study Instance UID"):
            again = write_ct_series(make_ct(seed=5), tmp_path / "ct2", reference=ABDOMEN)
        assert pydicom.dcmread(again[0]).StudyInstanceUID == ds.StudyInstanceUID
    assert errors_of("dciodvfy", files[0]) == []


def test_explicit_uids_win(tmp_path):
    files = write_ct_series(
        make_ct(), tmp_path / "ct", study_instance_uid="1.2.3.4", frame_of_reference_uid="1.2.3.5"
    )
    ds = pydicom.dcmread(files[-1])
    assert (ds.StudyInstanceUID, ds.FrameOfReferenceUID) == ("1.2.3.4", "1.2.3.5")


def test_rewrite_is_byte_identical_and_content_changes_uids(tmp_path):
    a = write_ct_series(make_ct(), tmp_path / "a")
    b = write_ct_series(make_ct(), tmp_path / "b")
    assert [f.read_bytes() for f in a] == [f.read_bytes() for f in b]
    changed = make_ct()
    changed.array[1, 2, 3] += 5.0
    c = write_ct_series(changed, tmp_path / "c")
    da, dc = pydicom.dcmread(a[0]), pydicom.dcmread(c[0])
    assert da.SeriesInstanceUID != dc.SeriesInstanceUID and da.SOPInstanceUID != dc.SOPInstanceUID
    assert da.StudyInstanceUID != dc.StudyInstanceUID  # anonymous study derived from content
    uids = {pydicom.dcmread(f).SOPInstanceUID for f in a + c}
    assert len(uids) == 8 and all(pydicom.uid.UID(u).is_valid for u in uids)


def test_failure_mid_series_leaves_nothing(tmp_path, monkeypatch):
    calls = []
    real_save = ct_series.save

    def failing_save(*args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        real_save(*args, **kwargs)

    monkeypatch.setattr(ct_series, "save", failing_save)
    with pytest.raises(KeyboardInterrupt):
        write_ct_series(make_ct(), tmp_path / "ct")
    assert list(tmp_path.iterdir()) == []
    calls.clear()
    with pytest.raises(KeyboardInterrupt):
        write_ct_series_4d([make_ct(), make_ct(seed=1)], tmp_path / "4d", phase_percent=[0, 50])
    assert list(tmp_path.iterdir()) == []


def test_failure_keeps_previous_series(tmp_path, monkeypatch):
    first = write_ct_series(make_ct(), tmp_path / "ct")
    before = [f.read_bytes() for f in first]
    monkeypatch.setattr(ct_series, "save", lambda *a, **k: (_ for _ in ()).throw(OSError("disk")))
    with pytest.raises(OSError, match="disk"):
        write_ct_series(make_ct(seed=3), tmp_path / "ct")
    assert [f.read_bytes() for f in first] == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ct"]


def test_bad_input_raises_dicom_error(tmp_path):
    image = make_ct()
    with pytest.raises(DicomError, match="must be a tetdose.core.image.Image"):
        write_ct_series(image.array[0], tmp_path / "x")
    nan = image.with_array(np.where(image.array > 1500, np.nan, image.array))
    with pytest.raises(DicomError, match="NaN"):
        write_ct_series(nan, tmp_path / "x")
    with pytest.raises(DicomError, match="one phase_percent per image"):
        write_ct_series_4d([image, image], tmp_path / "x", phase_percent=[0])
    with pytest.raises(DicomError, match="not distinct"):
        write_ct_series_4d([image, image], tmp_path / "x", phase_percent=[10.04, 10.03])
    with pytest.raises(DicomError, match="outside"):
        write_ct_series_4d([image], tmp_path / "x", phase_percent=[100])
    with pytest.raises(DicomError, match="does not exist"):
        write_ct_series(image, tmp_path / "x", reference=tmp_path / "nowhere")
    assert not (tmp_path / "x").exists()
    write_ct_series(image, tmp_path / "x")
    with pytest.raises(DicomError, match="overwrite=True"):
        write_ct_series(image, tmp_path / "x", overwrite=False)
