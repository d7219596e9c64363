"""``tetdose mesh`` inputs refused before meshing (issue 27): a body that is not there."""

from __future__ import annotations

import numpy as np
import pytest

from tetdose.cli import main
from tetdose.core.image import Image, ImageGrid
from tetdose.core.io import write_image
from tetdose.errors import ImageError
from tetdose.meshing.inputs import with_body


def _images(tmp_path, ct_origin_mm):
    grid = ImageGrid([0.0, 0.0, 0.0], [2.0, 2.0, 2.0], np.eye(3), (12, 12, 12))
    labels = np.zeros(grid.shape, dtype=np.uint8)
    labels[4:8, 4:8, 4:8] = 1
    ct_grid = ImageGrid(ct_origin_mm, [2.0, 2.0, 2.0], np.eye(3), (12, 12, 12))
    ct = np.full(ct_grid.shape, -1000, dtype=np.int16)
    ct[2:10, 2:10, 2:10] = 40
    write_image(tmp_path / "labels.nrrd", Image(labels, grid))
    write_image(tmp_path / "ct.nrrd", Image(ct, ct_grid))
    return Image(labels, grid), Image(ct, ct_grid)


def test_body_auto_with_a_ct_elsewhere_is_refused(tmp_path):
    labels, ct = _images(tmp_path, [500.0, 0.0, 0.0])
    with pytest.raises(ImageError, match="body outline does not overlap the label image"):
        with_body(labels, ct)
    _, here = _images(tmp_path, [0.0, 0.0, 0.0])
    out, body = with_body(labels, here)
    assert body == 2 and (out.array == 2).sum() == 8**3 - 4**3  # the outline around label 1


@pytest.mark.parametrize(("body", "message"), [
    ("9", "--body 9: the label image has no label 9 (its labels: [1])"),
    ("auto", "body outline does not overlap the label image"),
])
def test_cli_mesh_refuses_a_body_that_is_not_there(tmp_path, capsys, body, message):
    _images(tmp_path, [500.0, 0.0, 0.0])
    code = main(["mesh", "-q", "--labels", str(tmp_path / "labels.nrrd"), "--ct",
                 str(tmp_path / "ct.nrrd"), "--body", body, "-o", str(tmp_path / "m.vtu")])
    assert code == 2 and message in capsys.readouterr().err
    assert not (tmp_path / "m.vtu").exists()
