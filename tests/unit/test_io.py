"""Mesh and image I/O round trips, geometry through SimpleITK, atomic writes."""

import meshio
import numpy as np
import pytest
import SimpleITK as sitk

from tetdose._atomic import MARKER, atomic_write_dir, atomic_write_file
from tetdose.core.image import Image, ImageGrid
from tetdose.core.io import read_image, read_mesh, write_image, write_mesh
from tetdose.core.mesh import TetMesh
from tetdose.errors import ImageError, MeshError

from conftest import SHARED
from helpers import box_mesh


def test_vtu_round_trip_keeps_arrays_and_region(tmp_path):
    m = box_mesh([0, 0, 0], [2, 2, 2], (2, 1, 1))
    m = TetMesh(m.points_mm, m.tets, np.arange(m.n_tets) % 3,
                {"density": np.linspace(0, 1, m.n_points)}, {"extra": np.ones(m.n_tets)})
    write_mesh(tmp_path / "m.vtu", m)
    back = read_mesh(tmp_path / "m.vtu")
    np.testing.assert_array_equal(back.tets, m.tets)
    np.testing.assert_array_equal(back.region, m.region)
    np.testing.assert_allclose(back.point_data["density"], m.point_data["density"])
    np.testing.assert_allclose(back.cell_data["extra"], 1.0)


@pytest.mark.parametrize("ext", [".msh", ".inp", ".mesh", ".vtk"])
def test_other_formats_read(tmp_path, ext):
    m = box_mesh([0, 0, 0], [2, 2, 2], (1, 1, 1))
    kwargs = {"file_format": "gmsh22", "binary": False} if ext == ".msh" else {}
    meshio.write(tmp_path / f"m{ext}", meshio.Mesh(m.points_mm, [("tetra", m.tets)]), **kwargs)
    back = read_mesh(tmp_path / f"m{ext}")
    assert back.volumes_mm3.sum() == pytest.approx(8.0)


def test_bad_mesh_files_are_refused(tmp_path):
    tri = tmp_path / "surface.vtu"
    meshio.write(tri, meshio.Mesh(np.eye(3), [("triangle", np.array([[0, 1, 2]]))]))
    with pytest.raises(MeshError, match="no tetrahedra"):
        read_mesh(tri)
    junk = tmp_path / "junk.vtu"
    junk.write_text("not a mesh")
    with pytest.raises(MeshError, match="cannot read"):
        read_mesh(junk)
    p = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]])
    inv = tmp_path / "inverted.vtu"
    meshio.write(inv, meshio.Mesh(p, [("tetra", np.array([[0, 2, 1, 3]]))]))
    with pytest.raises(MeshError, match="inverted"):
        read_mesh(inv)
    assert read_mesh(inv, fix_orientation=True).signed_volumes_mm3[0] > 0


def test_image_geometry_matches_simpleitk(tmp_path):
    d = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]])
    grid = ImageGrid([10, -20, 5], [0.8, 1.2, 2.5], d, (5, 4, 3))
    img = Image(np.arange(60, dtype=np.int16).reshape(grid.shape), grid)
    s = img.to_sitk()
    for idx in [(0, 0, 0), (4, 3, 2), (2, 1, 1)]:
        np.testing.assert_allclose(grid.index_to_physical(np.array(idx, float)),
                                   s.TransformIndexToPhysicalPoint(idx))
    np.testing.assert_allclose(grid.affine[:3, :3] @ [1, 2, 3] + grid.affine[:3, 3],
                               s.TransformContinuousIndexToPhysicalPoint((1, 2, 3)))
    write_image(tmp_path / "a.nrrd", img)
    back = read_image(tmp_path / "a.nrrd")
    assert back.grid.same_as(grid)
    np.testing.assert_array_equal(back.array, img.array)
    write_image(tmp_path / "a.nii.gz", img)
    assert read_image(tmp_path / "a.nii.gz").grid.same_as(grid)


def test_non_orthonormal_direction_is_refused():
    with pytest.raises(ImageError, match="orthonormal"):
        ImageGrid([0, 0, 0], [1, 1, 1], [[1, 0.2, 0], [0, 1, 0], [0, 0, 1]], (2, 2, 2))


def test_unreadable_image_is_refused(tmp_path):
    (tmp_path / "x.nrrd").write_text("garbage")
    with pytest.raises(ImageError, match="cannot read"):
        read_image(tmp_path / "x.nrrd")
    with pytest.raises(ImageError, match="does not exist"):
        read_image(tmp_path / "nope.mha")


@pytest.mark.skipif(not (SHARED / "data/abdomen-dicom/series").exists(), reason="../shared absent")
def test_real_dicom_series_reads_with_its_geometry():
    img = read_image(SHARED / "data/abdomen-dicom/series")
    assert img.grid.size == (512, 512, 20)
    np.testing.assert_allclose(img.grid.spacing_mm[2], 2.0, atol=1e-3)
    assert -1100 < img.array.min() < -900 and img.array.max() > 500


def test_atomic_file_and_dir_leave_nothing_on_failure(tmp_path):
    with pytest.raises(RuntimeError), atomic_write_file(tmp_path / "out.vtu") as tmp:
        tmp.write_text("half")
        raise RuntimeError("boom")
    with pytest.raises(RuntimeError), atomic_write_dir(tmp_path / "series") as d:
        (d / "1.dcm").write_text("x")
        raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []
    with atomic_write_dir(tmp_path / "series") as d:
        (d / "1.dcm").write_text("x")
    with atomic_write_dir(tmp_path / "series") as d:  # overwrite replaces the whole folder
        (d / "2.dcm").write_text("y")
    # the folder holds the new file and the marker saying tetdose wrote it (and may replace it)
    assert sorted(p.name for p in (tmp_path / "series").iterdir()) == [MARKER, "2.dcm"]
    assert [p.name for p in tmp_path.iterdir()] == ["series"]


def test_sitk_reads_what_we_write_with_direction(tmp_path):
    grid = ImageGrid([1, 2, 3], [1, 1, 2], np.diag([1.0, -1.0, -1.0]), (3, 3, 2))
    write_image(tmp_path / "f.mha", Image(np.zeros(grid.shape, np.float32), grid))
    s = sitk.ReadImage(str(tmp_path / "f.mha"))
    np.testing.assert_allclose(s.GetDirection(), grid.direction.ravel())
