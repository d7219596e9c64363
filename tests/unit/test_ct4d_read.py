"""Reading a 4D-CT (tetdose.read_4dct): phase order, voxels, and the errors naming the series."""

from __future__ import annotations

import shutil

import numpy as np
import pydicom
import pytest

import tetdose
from tetdose.core.image import Image, ImageGrid
from tetdose.core.io import write_image
from tetdose.dicom import write_ct_series_4d
from tetdose.errors import ImageError
from tetdose.motion.ct4d_read import find_phase, read_4dct

GRID = ImageGrid([-10.0, 5.0, -30.0], [2.0, 1.5, 3.0], np.eye(3), (9, 7, 6))
PERCENTS = [0.0, 20.0, 40.0, 60.0, 80.0]


def phases(n: int = len(PERCENTS), grid: ImageGrid = GRID) -> list[Image]:
    rng = np.random.default_rng(12)
    return [Image(rng.integers(-1024, 3000, grid.shape).astype(np.int16), grid) for _ in range(n)]


@pytest.fixture
def ct4d(tmp_path):
    images = phases()
    write_ct_series_4d(images, tmp_path / "ct4d", phase_percent=PERCENTS)
    return tmp_path / "ct4d", images


def assert_phases(got, images, percents=PERCENTS):
    assert [p.percent for p in got] == percents
    for p, im in zip(got, images, strict=True):
        assert p.image.grid.same_as(im.grid)
        assert p.image.array.dtype == im.array.dtype
        np.testing.assert_array_equal(p.image.array, im.array)  # bitwise


def test_tetdose_4dct_reads_back_in_phase_order_bitwise(tmp_path):
    images = phases()
    # written in a scrambled percent order: the reader sorts, it does not trust folder names
    order = [3, 0, 4, 1, 2]
    folder = tmp_path / "ct4d"
    write_ct_series_4d([images[i] for i in order], folder, phase_percent=[PERCENTS[i] for i in order])
    # the writer numbers TemporalPositionIdentifier in writing order (3, 0, 4, 1, 2): the reader
    # orders by it, so the phases come back in that order with the description's percentages
    with pytest.warns(UserWarning, match="do not increase"):
        got = tetdose.read_4dct(folder)
    assert_phases(got, [images[i] for i in order], [PERCENTS[i] for i in order])
    assert "4D-CT 60%" in got[0].source


def test_shuffled_into_one_folder_reads_the_same(tmp_path):
    images = phases()
    write_ct_series_4d(images, tmp_path / "ct4d", phase_percent=PERCENTS)
    files = sorted((tmp_path / "ct4d").rglob("*.dcm"))
    flat = tmp_path / "flat"
    flat.mkdir()
    perm = np.random.default_rng(3).permutation(len(files))
    for i, f in zip(perm, files, strict=True):
        shutil.copy(f, flat / f"IM{i:05d}")  # names say nothing about phase or slice
    assert_phases(read_4dct(flat), images)
    assert_phases(read_4dct(tmp_path / "ct4d"), images)


def _rewrite(folder, edit):
    for f in sorted(folder.rglob("*.dcm")):
        ds = pydicom.dcmread(f)
        edit(ds)
        ds.save_as(f)


def test_order_falls_back_to_description_then_acquisition_time(tmp_path):
    images = phases(3)
    write_ct_series_4d(images, tmp_path / "a", phase_percent=[50.0, 0.0, 25.0])

    def drop_temporal(ds):
        del ds.TemporalPositionIdentifier

    _rewrite(tmp_path / "a", drop_temporal)
    got = read_4dct(tmp_path / "a")  # from "4D-CT 25%" etc.
    assert_phases(got, [images[1], images[2], images[0]], [0.0, 25.0, 50.0])

    times = {"4D-CT 50%": "101500", "4D-CT 0%": "101000", "4D-CT 25%": "100500"}

    def time_only(ds):
        ds.AcquisitionTime = times[ds.SeriesDescription]
        ds.SeriesDescription = "4D thorax"

    _rewrite(tmp_path / "a", time_only)
    got = read_4dct(tmp_path / "a")  # 25 % series first in time, then 0 %, then 50 %
    assert_phases(got, [images[2], images[1], images[0]], [0.0, 100 / 3, 200 / 3])

    def no_time(ds):
        del ds.AcquisitionTime

    _rewrite(tmp_path / "a", no_time)
    with pytest.raises(ImageError, match="no TemporalPositionIndex/TemporalPositionIdentifier") as e:
        read_4dct(tmp_path / "a")
    assert "SeriesDescription" in str(e.value) and "no AcquisitionTime" in str(e.value)
    assert "\n" not in str(e.value)


def test_missing_slice_names_the_series(ct4d):
    folder, _ = ct4d
    (folder / "phase_040" / "CT00003.dcm").unlink()
    with pytest.raises(ImageError, match=r"series '4D-CT 40%' .*slice spacing is not uniform"):
        read_4dct(folder)


def test_mixed_geometry_names_the_series(ct4d):
    folder, _ = ct4d
    f = folder / "phase_020" / "CT00002.dcm"
    ds = pydicom.dcmread(f)
    ds.PixelSpacing = [1.0, 1.0]
    ds.save_as(f)
    with pytest.raises(ImageError, match=r"series '4D-CT 20%' .*pixel spacing or orientation"):
        read_4dct(folder)


def test_image_files_ordered_by_name_percent(tmp_path):
    images = phases(3)
    paths = []
    for im, pct in zip(images, [60.0, 0.0, 30.0], strict=True):
        paths.append(write_image(tmp_path / f"phase_{pct:05.1f}.nrrd", im))
    got = read_4dct(paths)
    assert_phases(got, [images[1], images[2], images[0]], [0.0, 30.0, 60.0])
    assert_phases(read_4dct(tmp_path), [images[1], images[2], images[0]], [0.0, 30.0, 60.0])
    assert find_phase(got, 30.0) == 1
    with pytest.raises(ImageError, match="no 50 % phase"):
        find_phase(got, 50.0)
    named = [write_image(tmp_path / "x" / f"{n}.mha", im) for n, im in zip("cab", images,
                                                                             strict=True)]
    assert_phases(read_4dct(named), images, [0.0, 100 / 3, 200 / 3])  # given order kept


def test_empty_folder_and_missing_path(tmp_path):
    (tmp_path / "e").mkdir()
    (tmp_path / "e" / "notes.txt").write_text("hello")
    with pytest.raises(ImageError, match="no CT series and no image files"):
        read_4dct(tmp_path / "e")
    with pytest.raises(ImageError, match="does not exist"):
        read_4dct(tmp_path / "nope")


def test_image_files_with_a_name_without_percent_or_twice_are_refused(tmp_path):
    """Issue 27: one name without a % dropped every percentage (phase_050 became the 0 %
    reference); a duplicated file did the same."""
    images = phases(3)
    files = [write_image(tmp_path / n, im) for n, im in
             zip(["phase_050.0.nrrd", "phase_000.0.nrrd", "ref.nrrd"], images, strict=True)]
    with pytest.raises(tetdose.errors.OptionError, match="ref.nrrd carries no phase number while"):
        read_4dct(files)
    with pytest.raises(ImageError, match="phase_000.0.nrrd is given twice"):
        read_4dct([files[0], files[1], files[1]])
    copy = shutil.copy(files[1], tmp_path / "ct_0%.nrrd")
    with pytest.raises(tetdose.errors.OptionError, match="both name phase 0"):
        read_4dct([files[0], files[1], copy])
    got = read_4dct(files[:2])  # the names' percentages: 0 % first
    assert_phases(got, [images[1], images[0]], [0.0, 50.0])


def test_series_mixing_percent_and_no_percent_descriptions_are_refused(tmp_path):
    write_ct_series_4d(phases(3), tmp_path / "a", phase_percent=[0.0, 25.0, 50.0])

    def average(ds):
        if ds.SeriesDescription == "4D-CT 50%":
            ds.SeriesDescription = "AVG"

    _rewrite(tmp_path / "a", average)
    with pytest.raises(ImageError, match="series 'AVG' .* has no phase percentage"):
        read_4dct(tmp_path / "a")


def test_dose4d_phase_missing_from_the_4dct_says_what_to_do(tmp_path, capsys):
    """Issue 27: dose4d told the user to "pick one of these" phases; it has nothing to pick."""
    from tetdose.cli import main
    from tetdose.motion import BreathingModel
    from tetdose.motion.conserve import update_series

    from helpers import box_mesh

    mesh = box_mesh([-4, -4, -4], [4, 4, 4], (2, 2, 2))
    mesh = mesh.with_data(point_data={"density": np.ones(mesh.n_points)})
    series, _ = update_series(BreathingModel(2.0).series(mesh, 4))  # 0, 25, 50, 75 %
    series.write(tmp_path / "phases")
    for pct, im in zip((0.0, 50.0), phases(2), strict=True):
        write_image(tmp_path / f"phase_{pct:05.1f}.nrrd", im)
    (tmp_path / "plan.toml").write_text('[[beam]]\ntype = "pencil"\nenergy_mev = 1.0\n'
                                        'position_mm = [0, 0, -50.0]\ndirection = [0, 0, 1]\n')
    code = main(["dose4d", "-q", "--phases", str(tmp_path / "phases"), "--plan",
                 str(tmp_path / "plan.toml"), "--ct4d", str(tmp_path / "phase_000.0.nrrd"),
                 str(tmp_path / "phase_050.0.nrrd"), "-o", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert code == 2 and "no 25 % phase for the phase mesh at 25 %" in err
    assert "pick one" not in err and "tetdose deform --4dct" in err
