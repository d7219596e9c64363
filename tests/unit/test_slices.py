"""Slice figures: mesh surfaces cut by the slice plane (analytic perimeters), frames in mm, and
the dose-slice figure with its CT wash, isodoses and contours."""

import json

import numpy as np
import pytest

from tetdose.compare.dvh import dvh
from tetdose.compare.report import dose_slices_figure, dvh_figure, write_report
from tetdose.compare.slices import SliceFrame, plane_section, region_faces
from tetdose.core.image import Image, ImageGrid

from helpers import box_mesh


def _length(segments):
    return float(np.linalg.norm(segments[:, 1] - segments[:, 0], axis=1).sum())


def test_plane_cut_of_a_triangle_is_the_analytic_segment():
    tri = np.array([[[0.0, 0.0, -1.0], [2.0, 0.0, 1.0], [0.0, 2.0, 1.0]]])
    seg = plane_section(tri, 0.0)
    assert seg.shape == (1, 2, 2)
    assert sorted(map(tuple, np.round(seg[0], 12))) == [(0.0, 1.0), (1.0, 0.0)]
    assert plane_section(tri, 5.0).shape == (0, 2, 2)


@pytest.mark.parametrize("z", [0.5, 1.0, 2.25])  # 1.0 lies on a layer of vertices
def test_section_of_a_box_surface_is_its_perimeter(z):
    mesh = box_mesh([0, 0, 0], [4, 3, 3], (4, 3, 3))
    seg = plane_section(region_faces(mesh), z)
    assert _length(seg) == pytest.approx(2 * (4 + 3), rel=1e-9)


def test_region_surface_includes_the_interface():
    mesh = box_mesh([0, 0, 0], [4, 4, 4], (4, 4, 4))
    region = (mesh.centroids_mm[:, 0] > 2.0).astype(int)
    mesh = type(mesh)(mesh.points_mm, mesh.tets, region)
    seg = plane_section(region_faces(mesh, 1), 2.5)
    assert _length(seg) == pytest.approx(2 * (2 + 4), rel=1e-9)  # a 2 × 4 rectangle


def _dose_image(direction=None):
    grid = ImageGrid(origin_mm=[-10.0, -20.0, 0.0], spacing_mm=[1.0, 2.0, 1.0],
                     direction=np.eye(3) if direction is None else direction, size=(21, 21, 5))
    z, y, x = np.meshgrid(np.arange(5), np.arange(21), np.arange(21), indexing="ij")
    return Image(np.exp(-((x - 10) ** 2 + (y - 10) ** 2) / 40.0) * 2.0, grid)


def test_slice_frame_extent_and_flip_are_in_patient_mm():
    a = _dose_image()
    f = SliceFrame(a, 2)
    assert f.extent == pytest.approx([-10.5, 10.5, -21.0, 21.0])
    assert f.z_mm == pytest.approx(2.0)
    flipped = SliceFrame(_dose_image(np.diag([-1.0, 1.0, 1.0])), 0)
    assert flipped.extent[:2] == pytest.approx([-9.5, -30.5])  # x decreases with i
    assert flipped.to_display(np.array([[1.0, 0.0]]))[0, 0] == pytest.approx(-11.0)


def test_dose_slice_figure_has_ct_isodoses_contours(tmp_path):
    a = _dose_image()
    ct = a.with_array(np.full(a.array.shape, -200.0))
    mesh = box_mesh([-5, -10, 0.5], [5, 10, 3.5], (2, 2, 3))
    fig = dose_slices_figure(a, a.with_array(a.array * 0.9), k=2, unit="Gy", ct_hu=ct, mesh=mesh,
                             prescription_gy=2.0)
    assert fig.png[:8] == b"\x89PNG\r\n\x1a\n" and len(fig.png) > 10_000
    assert fig.data["isodose_gy"] == pytest.approx([1.9, 1.0, 0.4])
    assert fig.data["contour_segments"]["mesh"] > 0
    h = dvh(np.linspace(0, 2, 50), np.ones(50), name="mesh")
    figs = [fig, dvh_figure({"tumour": [h]}, unit="Gy")]
    out = write_report(tmp_path / "r", figs, {"n": 1})
    for f in figs:
        assert (out / f"{f.name}.png").stat().st_size > 5_000
    assert "D95" in json.dumps(json.loads((out / "figures.json").read_text())["dvh"])
