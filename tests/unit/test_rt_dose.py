"""RT Dose writer: dciodvfy/dcentvfy validity together with the CT it belongs to, grid and
values read back by SimpleITK (GDCM) and pydicom within DoseGridScaling, plan reference,
determinism, atomicity and input checks.
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import numpy as np
import pydicom
import pytest
import SimpleITK as sitk

import tetdose.dicom.rt_dose as rt_dose
from tetdose.core.image import Image, ImageGrid
from tetdose.dicom import rt_plan_path, write_ct_series, write_rt_dose
from tetdose.errors import DicomError

ROT = np.array(
    [[0.6, -0.8, 0.0], [0.8, 0.6, 0.0], [0.0, 0.0, 1.0]]
) @ np.array([[1.0, 0.0, 0.0], [0.0, 0.8, -0.6], [0.0, 0.6, 0.8]])  # fmt: skip
DIRECTIONS = {"identity": np.eye(3), "oblique": ROT, "y_flipped": np.diag([1.0, -1.0, 1.0])}


def make_dose(direction=None, seed: int = 0, size=(6, 5, 4)) -> Image:
    d = np.eye(3) if direction is None else direction
    grid = ImageGrid((-20.0, 10.0, -150.0), (2.0, 2.5, 3.0), d, size)
    dose = np.random.default_rng(seed).gamma(2.0, 0.8, grid.shape)
    dose[0, 0, 0] = 0.0
    return Image(dose, grid)


def errors_of(tool: str, *paths: Path) -> list[str]:
    if shutil.which(tool) is None:
        pytest.skip(f"{tool} (Debian package dicom3tools) is not installed")
    run = subprocess.run([tool, *map(str, paths)], capture_output=True, text=True, check=False)
    return [line for line in (run.stdout + run.stderr).splitlines() if "Error" in line]


@pytest.fixture
def ct_folder(tmp_path) -> Path:
    grid = ImageGrid((-20.0, 10.0, -150.0), (1.0, 1.0, 3.0), np.eye(3), (12, 12, 4))
    hu = np.random.default_rng(9).uniform(-1000, 1000, grid.shape)
    write_ct_series(Image(hu, grid), tmp_path / "ct")
    return tmp_path / "ct"


def read_dose(path: Path) -> Image:
    """SimpleITK grid; values = stored × DoseGridScaling (SimpleITK returns stored integers)."""
    image = Image.from_sitk(sitk.ReadImage(str(path)))
    scaling = float(pydicom.dcmread(path, stop_before_pixels=True).DoseGridScaling)
    return image.with_array(image.array.astype(np.float64) * scaling)


@pytest.mark.parametrize("bits", [16, 32])
@pytest.mark.parametrize("name", DIRECTIONS)
def test_round_trip_within_dose_grid_scaling(tmp_path, name, bits):
    dose = make_dose(DIRECTIONS[name])
    path = write_rt_dose(dose, tmp_path / "rd.dcm", frame_of_reference_uid="1.2.3", bits=bits)
    scaling = float(pydicom.dcmread(path).DoseGridScaling)
    assert scaling <= dose.array.max() / (2**bits - 1) * (1 + 1e-6)
    read = read_dose(path)
    np.testing.assert_allclose(read.grid.spacing_mm, dose.grid.spacing_mm, atol=1e-6)
    index = dose.grid.physical_to_index(read.grid.voxel_centers_mm())
    np.testing.assert_allclose(index, np.rint(index), atol=1e-5)
    i, j, k = np.rint(index).astype(int).T
    assert sorted(zip(i, j, k, strict=True)) == sorted(np.ndindex(*dose.grid.size))
    np.testing.assert_allclose(read.array.ravel(), dose.array[k, j, i], atol=scaling / 2 * 1.001)
    if name != "y_flipped":
        np.testing.assert_allclose(read.grid.origin_mm, dose.grid.origin_mm, atol=1e-5)
        np.testing.assert_allclose(read.grid.direction, dose.grid.direction, atol=1e-6)


def test_dose_joins_ct_study_and_frame_and_validates(tmp_path, ct_folder):
    path = write_rt_dose(make_dose(), tmp_path / "rd.dcm", reference_ct=ct_folder)
    plan = rt_plan_path(path)
    ct = pydicom.dcmread(sorted(ct_folder.iterdir())[0])
    ds = pydicom.dcmread(path)
    assert ds.SOPClassUID == pydicom.uid.RTDoseStorage and ds.Modality == "RTDOSE"
    assert ds.FrameOfReferenceUID == ct.FrameOfReferenceUID
    assert ds.StudyInstanceUID == ct.StudyInstanceUID and ds.PatientID == ct.PatientID
    assert ds.SeriesInstanceUID != ct.SeriesInstanceUID
    assert (ds.DoseUnits, ds.DoseType, ds.DoseSummationType) == ("GY", "PHYSICAL", "PLAN")
    assert ds.NumberOfFrames == 4 and ds.FrameIncrementPointer == 0x3004000C
    np.testing.assert_allclose(ds.GridFrameOffsetVector, [0.0, 3.0, 6.0, 9.0])
    assert (ds.BitsAllocated, ds.BitsStored, ds.PixelRepresentation) == (16, 16, 0)
    plan_ds = pydicom.dcmread(plan)
    assert plan_ds.SOPClassUID == pydicom.uid.RTPlanStorage
    ref = ds.ReferencedRTPlanSequence[0]
    assert ref.ReferencedSOPInstanceUID == plan_ds.SOPInstanceUID
    assert ref.ReferencedSOPClassUID == pydicom.uid.RTPlanStorage
    assert errors_of("dciodvfy", path) == []
    assert errors_of("dciodvfy", plan) == []
    assert errors_of("dcentvfy", path, plan, *sorted(ct_folder.iterdir())) == []


def test_pydicom_values_and_geometry(tmp_path):
    dose = make_dose(DIRECTIONS["oblique"])
    ds = pydicom.dcmread(write_rt_dose(dose, tmp_path / "rd.dcm", frame_of_reference_uid="1.2"))
    np.testing.assert_allclose(ds.ImagePositionPatient, dose.grid.origin_mm)
    np.testing.assert_allclose(ds.ImageOrientationPatient, dose.grid.direction[:, :2].T.ravel())
    np.testing.assert_allclose(ds.PixelSpacing, [2.5, 2.0])
    values = ds.pixel_array * float(ds.DoseGridScaling)
    assert values.shape == dose.array.shape
    np.testing.assert_allclose(values, dose.array, atol=float(ds.DoseGridScaling) / 2 * 1.001)


def test_given_plan_uid_is_referenced_and_no_plan_written(tmp_path):
    path = write_rt_dose(
        make_dose(), tmp_path / "rd.dcm", frame_of_reference_uid="1.2", referenced_rt_plan_uid="1.9"
    )
    assert pydicom.dcmread(path).ReferencedRTPlanSequence[0].ReferencedSOPInstanceUID == "1.9"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rd.dcm"]


def test_rewrite_is_byte_identical(tmp_path):
    a = write_rt_dose(make_dose(), tmp_path / "a.dcm", frame_of_reference_uid="1.2")
    b = write_rt_dose(make_dose(), tmp_path / "b.dcm", frame_of_reference_uid="1.2")
    assert a.read_bytes() == b.read_bytes()
    assert rt_plan_path(a).read_bytes() == rt_plan_path(b).read_bytes()
    c = write_rt_dose(make_dose(seed=1), tmp_path / "c.dcm", frame_of_reference_uid="1.2")
    assert pydicom.dcmread(a).SOPInstanceUID != pydicom.dcmread(c).SOPInstanceUID


def test_zero_dose_is_valid(tmp_path):
    zero = make_dose().with_array(np.zeros((4, 5, 6)))
    path = write_rt_dose(zero, tmp_path / "rd.dcm", frame_of_reference_uid="1.2")
    assert np.all(read_dose(path).array == 0.0)


def test_failure_leaves_neither_dose_nor_plan(tmp_path, monkeypatch):
    real_save = rt_dose.save

    def fail_on_dose(ds, path, sop_class, uid):
        if ds.Modality == "RTDOSE":
            raise KeyboardInterrupt
        real_save(ds, path, sop_class, uid)

    monkeypatch.setattr(rt_dose, "save", fail_on_dose)
    with pytest.raises(KeyboardInterrupt):
        write_rt_dose(make_dose(), tmp_path / "rd.dcm", frame_of_reference_uid="1.2")
    assert list(tmp_path.iterdir()) == []


def test_missing_frame_of_reference_warns(tmp_path):
    with pytest.warns(UserWarning, match="Frame of Reference"):
        write_rt_dose(make_dose(), tmp_path / "rd.dcm")


def test_bad_input_raises_dicom_error(tmp_path):
    dose = make_dose()
    kw = {"frame_of_reference_uid": "1.2"}
    with pytest.raises(DicomError, match="negative"):
        write_rt_dose(dose.with_array(dose.array - 1.0), tmp_path / "x.dcm", **kw)
    with pytest.raises(DicomError, match="NaN"):
        write_rt_dose(dose.with_array(dose.array * np.nan), tmp_path / "x.dcm", **kw)
    with pytest.raises(DicomError, match="must be a tetdose.core.image.Image"):
        write_rt_dose(dose.array, tmp_path / "x.dcm", **kw)
    with pytest.raises(DicomError, match="single slice"):
        write_rt_dose(make_dose(size=(6, 5, 1)), tmp_path / "x.dcm", **kw)
    with pytest.raises(DicomError, match="bits"):
        write_rt_dose(dose, tmp_path / "x.dcm", bits=8, **kw)
    with pytest.raises(DicomError, match="not supported"):
        write_rt_dose(dose, tmp_path / "x.dcm", summation_type="BEAM", **kw)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(("unit", "units"), [("Gy", "GY"), ("Gy per fraction", "GY"),
                                             ("Gy per source photon", "RELATIVE")])
def test_dose_units_follow_the_dose_unit(tmp_path, unit, units):
    """An unprescribed dose (Gy per source photon) is not an absolute dose: DoseUnits RELATIVE
    (PS3.3 C.8.8.3 allows GY or RELATIVE), and the comment and description say per photon."""
    dose = make_dose()
    with pytest.warns(UserWarning, match="Frame of Reference"):
        path = write_rt_dose(dose, tmp_path / "d.dcm", unit=unit)
    ds = pydicom.dcmread(path)
    assert ds.DoseUnits == units and ds.DoseComment == f"dose to medium in {unit}"
    assert ("source photon" in ds.SeriesDescription) == (units == "RELATIVE")
    np.testing.assert_allclose(read_dose(path).array, dose.array,
                               atol=float(ds.DoseGridScaling) / 2)


def test_dose_to_water_is_stated_in_comment_and_description(tmp_path):
    with pytest.warns(UserWarning, match="Frame of Reference"):
        path = write_rt_dose(make_dose(), tmp_path / "d.dcm", unit="Gy", dose_to="water")
    ds = pydicom.dcmread(path)
    assert ds.DoseComment == "dose to water in Gy" and ds.SeriesDescription.endswith("to water")
    with pytest.raises(DicomError, match="dose_to 'ink'"):
        write_rt_dose(make_dose(), tmp_path / "e.dcm", dose_to="ink")


def test_unknown_dose_unit_is_refused(tmp_path):
    with pytest.raises(DicomError, match="dose unit 'cGy' is unknown"):
        write_rt_dose(make_dose(), tmp_path / "d.dcm", unit="cGy", frame_of_reference_uid="1.2.3")
    assert list(tmp_path.iterdir()) == []


def test_export_dose_of_an_unprescribed_dose_is_relative(tmp_path, ct_folder):
    """tetdose export-dose reads the unit from the run record beside the dose (none: per photon)."""
    import json

    from tetdose.cli import main
    from tetdose.core.io import write_image

    grid = Image.from_sitk(sitk.ReadImage(
        sitk.ImageSeriesReader.GetGDCMSeriesFileNames(str(ct_folder)))).grid
    write_image(tmp_path / "dose.nrrd", Image(np.ones(grid.shape, np.float32), grid))
    assert main(["export-dose", "--dose", str(tmp_path / "dose.nrrd"), "--like", str(ct_folder),
                 "-o", str(tmp_path / "photon.dcm")]) == 0
    assert pydicom.dcmread(tmp_path / "photon.dcm").DoseUnits == "RELATIVE"
    (tmp_path / "dose.json").write_text(json.dumps({"units": {"dose": "Gy per fraction"}}))
    assert main(["export-dose", "--dose", str(tmp_path / "dose.nrrd"), "--like", str(ct_folder),
                 "-o", str(tmp_path / "fraction.dcm")]) == 0
    assert pydicom.dcmread(tmp_path / "fraction.dcm").DoseUnits == "GY"
