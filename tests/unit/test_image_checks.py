"""Checks at the library boundary: what a CT may hold, DICOM slice geometry, densities, gamma
criteria — each refused with the tetdose error class that names it."""

from __future__ import annotations

import numpy as np
import pydicom
import pytest

from tetdose.compare.gamma import gamma_index
from tetdose.core.image import CT_HU_RANGE, Image, check_ct_hu
from tetdose.core.io import read_image
from tetdose.core.overlap import compute_overlap
from tetdose.core.voxelize import voxelize
from tetdose.dicom.ct_series import write_ct_series
from tetdose.errors import DensityError, DoseError, ImageError, OptionError

from helpers import box_mesh, grid_for

GRID = grid_for([0, 0, 0], [8, 6, 4], [1.0, 1.0, 1.0])


def _ct(values: np.ndarray) -> Image:
    return Image(np.broadcast_to(values, GRID.shape).copy(), GRID)


@pytest.mark.parametrize("dtype", [np.int16, np.int32, np.float32, np.float64])
def test_signed_hu_pass(dtype):
    ct = _ct(np.linspace(-1000, 1500, GRID.size[0]).astype(dtype))
    assert check_ct_hu(ct) is ct


@pytest.mark.parametrize(("array", "words"), [
    (np.full(GRID.shape, 64536, np.uint16), ["uint16", "64536", "wrapped"]),  # −1000 HU wrapped
    (np.full(GRID.shape, 24, np.uint16), ["uint16", "signed HU"]),  # even in range: no air
    (np.full(GRID.shape, -100, np.int8), ["int8"]),
    (np.full(GRID.shape, CT_HU_RANGE[1] + 1, np.int32), ["outside the HU range"]),
    (np.full(GRID.shape, 1.05, np.float32) * np.nan, ["NaN", "i=0, j=0, k=0"]),
    (np.full(GRID.shape, True), ["bool"]),
])
def test_what_cannot_be_a_ct_is_refused_saying_what_was_found(array, words):
    with pytest.raises(ImageError) as err:
        check_ct_hu(Image(array, GRID), "ct.nrrd")
    for word in words:
        assert word in str(err.value)


def _series(tmp_path):
    hu = np.arange(GRID.n_voxels, dtype=np.int16).reshape(GRID.shape) - 500
    return write_ct_series(Image(hu, GRID), tmp_path / "ct")


def _edit_positions(files, shift_mm):
    for k, f in enumerate(files):
        ds = pydicom.dcmread(f)
        pos = [float(v) for v in ds.ImagePositionPatient]
        ds.ImagePositionPatient = [f"{p + s:.6f}" for p, s in zip(pos, shift_mm(k), strict=True)]
        ds.save_as(f)


def test_round_off_in_slice_positions_is_accepted(tmp_path):
    files = _series(tmp_path)
    jitter = np.random.default_rng(0).uniform(-2e-3, 2e-3, (len(files), 3))
    _edit_positions(files, lambda k: jitter[k] * [1, 1, 0])
    img = read_image(tmp_path / "ct")
    assert img.grid.size == GRID.size


def test_tilted_series_is_refused_with_its_angle(tmp_path):
    files = _series(tmp_path)
    tilt = np.tan(np.radians(5.0))  # 5° gantry tilt: slices shift by Δz·tan 5° along y
    _edit_positions(files, lambda k: [0.0, k * GRID.spacing_mm[2] * tilt, 0.0])
    with pytest.raises(ImageError, match=r"≈ 5\.00°.*refused, not resampled"):
        read_image(tmp_path / "ct")


def test_voxelize_refuses_bad_density_and_background():
    mesh = box_mesh([1, 1, 1], [7, 5, 3], (2, 2, 1))
    rho = np.ones(mesh.n_points)
    for background in (-3.0, float("nan"), "water"):
        with pytest.raises(OptionError, match="background"):
            voxelize(mesh, rho, GRID, background=background)
    bad = rho.copy()
    bad[3] = np.nan
    with pytest.raises(DensityError, match="1 of .* NaN"):
        voxelize(mesh, bad, GRID)
    voxelize(mesh, rho - 0.5, GRID)  # allowed here: warned where made, refused by the CLI


def test_monte_carlo_overlap_needs_a_sample():
    mesh = box_mesh([1, 1, 1], [7, 5, 3], (1, 1, 1))
    for n in (0, -10):
        with pytest.raises(OptionError, match="≥ 1 point"):
            compute_overlap(mesh, GRID, method="monte-carlo", n_samples=n)


def test_gamma_never_reports_a_nan_pass_rate():
    dose = Image(np.random.default_rng(1).uniform(0.5, 1.0, GRID.shape), GRID)
    assert 0 <= gamma_index(dose, dose).pass_rate_percent == 100.0
    with pytest.raises(OptionError, match=r"\[0, 100\)"):
        gamma_index(dose, dose, threshold_percent=150)
    zero = dose.with_array(np.zeros(GRID.shape))
    with pytest.raises(DoseError, match="zero everywhere"):
        gamma_index(zero, dose)
    with pytest.raises(DoseError, match="lower the threshold"):
        gamma_index(dose, dose, mask=np.zeros(GRID.shape, bool))
    with pytest.raises(DoseError, match="NaN"):
        gamma_index(dose, dose.with_array(dose.array * np.nan))
    assert issubclass(DoseError, ValueError) and issubclass(OptionError, ValueError)


def test_a_density_image_given_as_ct_is_refused():
    """A density image [g/cm³] (0.001…1.9) read as HU became ≈ 1 g/cm³ everywhere, silently."""
    rho = np.linspace(0.0012, 1.92, GRID.n_voxels).reshape(GRID.shape).astype(np.float32)
    with pytest.raises(ImageError, match=r"fractional values 0.0012…1.92: a density image"):
        check_ct_hu(Image(rho, GRID), "rho.nrrd")
    water = Image(np.zeros(GRID.shape, np.float32), GRID)  # 0 HU everywhere: a water CT
    assert check_ct_hu(water) is water
    whole = Image(np.round(rho * 2), GRID)  # whole numbers: HU near water, not densities
    assert check_ct_hu(whole) is whole


def test_a_background_density_in_hu_is_refused(tmp_path, capsys):
    from tetdose.cli import main

    code = main(["4dct", "--phases", str(tmp_path), "--like", str(tmp_path / "ct.nrrd"),
                 "--background", "1000", "-o", str(tmp_path / "out")])
    assert code == 2 and "denser than any material" in capsys.readouterr().err
