"""Tilted, sheared or skewed DICOM CT series: refused by default, resampled onto an orthogonal
grid on request (tetdose.core.tilted). The series hold a linear HU field sampled at the true voxel
positions, so linear interpolation must give it back exactly inside the stack."""

from __future__ import annotations

import numpy as np
import pydicom
import pytest

from tetdose.core.image import Image, ImageGrid
from tetdose.core.io import read_ct, read_image, tilted_policy
from tetdose.core.tilted import OUTSIDE_HU
from tetdose.dicom.ct_series import write_ct_series
from tetdose.errors import ImageError

SIZE = (10, 8, 6)  # columns, rows, slices
SPACING = 2.0  # mm, in-plane and between slices


def field_hu(x: np.ndarray) -> np.ndarray:
    """HU = −200 + 10 x + 5 y + 3 z [mm]: a linear field, integer on the grids below."""
    return -200.0 + 10.0 * x[..., 0] + 5.0 * x[..., 1] + 3.0 * x[..., 2]


def tilted_series(folder, row, col, shift_per_slice) -> None:  # noqa: ANN001
    """A series whose voxel (i, j, k) lies at i·2·row + j·2·col + k·(2 e_z + shift) [mm] and
    holds field_hu there."""
    row, col, shift = (np.asarray(v, float) for v in (row, col, shift_per_slice))
    step = np.array([0.0, 0.0, SPACING]) + shift
    k, j, i = np.meshgrid(*(np.arange(n) for n in SIZE[::-1]), indexing="ij")
    x = (i[..., None] * SPACING * row + j[..., None] * SPACING * col + k[..., None] * step)
    grid = ImageGrid((0, 0, 0), (SPACING,) * 3, np.eye(3), SIZE)
    files = write_ct_series(Image(np.round(field_hu(x)).astype(np.int16), grid), folder)
    for f in files:
        ds = pydicom.dcmread(f)
        kk = round(float(ds.ImagePositionPatient[2]) / SPACING)
        ds.ImageOrientationPatient = [*row.tolist(), *col.tolist()]
        ds.ImagePositionPatient = (kk * step).tolist()
        ds.save_as(f)


CASES = {"gantry tilt": ([1, 0, 0], [0, 1, 0], [0, 0.4, 0]),
         "sheared in x and y": ([1, 0, 0], [0, 1, 0], [0.4, -0.2, 0]),
         "skewed orientation": ([1, 0, 0], [0.6, 0.8, 0], [0, 0, 0])}


@pytest.mark.parametrize("case", CASES)
def test_tilted_series_is_refused_naming_the_option(tmp_path, case):
    tilted_series(tmp_path / "s", *CASES[case])
    with pytest.raises(ImageError, match=r"not resampled — rerun with --resample-tilted"):
        read_image(tmp_path / "s")


@pytest.mark.parametrize("case", CASES)
def test_tilted_series_is_resampled_on_request(tmp_path, case):
    row, col, shift = CASES[case]
    tilted_series(tmp_path / "s", row, col, shift)
    with pytest.warns(UserWarning, match="resampled onto an orthogonal grid"):
        ct = read_ct(tmp_path / "s", resample_tilted=True)
    g = ct.grid
    np.testing.assert_allclose(g.direction.T @ g.direction, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(g.spacing_mm[:2], [SPACING, SPACING], rtol=1e-12)  # in-plane kept
    # every output voxel whose centre lies inside the stack holds the field there
    centres = g.voxel_centers_mm().reshape(*g.shape, 3)
    a = np.column_stack([SPACING * np.asarray(row, float), SPACING * np.asarray(col, float),
                         np.array([0, 0, SPACING]) + shift])
    idx = np.linalg.solve(a, centres.reshape(-1, 3).T).T.reshape(centres.shape)
    upper = np.array(SIZE) - 1
    inside = np.all((idx >= 1e-6) & (idx <= upper - 1e-6), axis=-1)
    # outside the stack's voxels (SimpleITK extends the stack by half a voxel at its faces)
    outside = np.any((idx < -0.501) | (idx > upper + 0.501), axis=-1)
    assert inside.sum() > 0.3 * np.prod(SIZE) and outside.any()
    np.testing.assert_allclose(ct.array[inside], field_hu(centres[inside]), atol=2e-3)
    assert np.all(ct.array[outside] == OUTSIDE_HU)


def test_policy_sets_the_default_and_an_orthogonal_series_is_read_unchanged(tmp_path):
    tilted_series(tmp_path / "t", *CASES["gantry tilt"])
    tilted_series(tmp_path / "o", [1, 0, 0], [0, 1, 0], [0, 0, 0])
    with tilted_policy(True), pytest.warns(UserWarning, match="resampled"):
        assert read_image(tmp_path / "t").grid.size[1] > SIZE[1]  # the tilt widens y
    straight = read_image(tmp_path / "o")
    assert straight.grid.size == SIZE and straight.array.dtype != np.float32
    k, j, i = np.meshgrid(*(np.arange(n) for n in SIZE[::-1]), indexing="ij")
    x = np.stack([i, j, k], axis=-1) * SPACING
    np.testing.assert_array_equal(straight.array, field_hu(x))
