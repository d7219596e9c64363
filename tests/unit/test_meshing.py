"""Tests for tetdose.meshing (marching cubes + gmsh); skipped without the ``meshing`` extra."""

from __future__ import annotations

import math
import multiprocessing
import sys
import warnings

import numpy as np
import pytest

from tetdose.core.image import Image, ImageGrid
from tetdose.core.io import read_mesh, write_image
from tetdose.errors import ImageError, MeshError, TetdoseError

pytest.importorskip("gmsh", reason="gmsh not installed (extra tetdose[meshing])")
pytest.importorskip("skimage", reason="scikit-image not installed (extra tetdose[meshing])")

from tetdose import meshing  # noqa: E402
from tetdose.cli import main  # noqa: E402

RADIUS_MM = 20.0
SPACING_MM = 1.5
N_VOX = 32


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


def _ball_image(direction: np.ndarray | None = None, centre_mm=(0.0, 0.0, 0.0),
                radius_mm: float = RADIUS_MM) -> Image:
    """Label 1 inside a ball of ``radius_mm`` about ``centre_mm`` (physical), 0 elsewhere."""
    direction = np.eye(3) if direction is None else direction
    half = np.full(3, (N_VOX - 1) * SPACING_MM / 2)
    origin = np.asarray(centre_mm) - direction @ half + 0.3  # off-centre of the voxel lattice
    grid = ImageGrid(origin, (SPACING_MM,) * 3, direction, (N_VOX,) * 3)
    r = np.linalg.norm(grid.voxel_centers_mm() - np.asarray(centre_mm), axis=1)
    return Image((r <= radius_mm).astype(np.int16).reshape(grid.shape), grid)


def _label_at(image: Image, points_mm: np.ndarray) -> np.ndarray:
    """Label of the voxel containing each point, by inverting the 4×4 affine (−1 outside)."""
    homog = np.c_[points_mm, np.ones(len(points_mm))]
    idx = np.rint((np.linalg.inv(image.grid.affine) @ homog.T).T[:, :3]).astype(int)
    ok = np.all((idx >= 0) & (idx < np.array(image.grid.size)), axis=1)
    out = np.full(len(points_mm), -1)
    out[ok] = image.array[idx[ok, 2], idx[ok, 1], idx[ok, 0]]
    return out


def _edges_mm(mesh) -> np.ndarray:  # noqa: ANN001
    p = mesh.points_mm[mesh.tets]
    return np.linalg.norm(p[:, [1, 2, 3, 2, 3, 3]] - p[:, [0, 0, 0, 1, 1, 2]], axis=2)


@pytest.fixture(scope="module")
def ball() -> Image:
    return _ball_image()


@pytest.fixture(scope="module")
def ball_mesh(ball):  # noqa: ANN001, ANN201
    return meshing.mesh_label_image(ball, [1], 4.0)


def test_ball_volume_matches_mask_and_analytic(ball, ball_mesh) -> None:  # noqa: ANN001
    volume = ball_mesh.volumes_mm3.sum()
    assert volume == pytest.approx(ball.array.sum() * SPACING_MM**3, rel=0.03)
    assert volume == pytest.approx(4.0 / 3.0 * math.pi * RADIUS_MM**3, rel=0.03)


def test_ball_cells_positive_and_not_degenerate(ball_mesh) -> None:  # noqa: ANN001
    inverted, degenerate = ball_mesh.bad_cells()
    assert len(inverted) == 0 and len(degenerate) == 0
    assert (ball_mesh.signed_volumes_mm3 > 0).all()
    quality = 6 * math.sqrt(2) * ball_mesh.volumes_mm3 / _edges_mm(ball_mesh).max(axis=1) ** 3
    assert quality.min() > 0.02  # 1 for a regular tetrahedron; slivers would be ~0
    assert (ball_mesh.region == 1).all()
    assert ball_mesh.neighbors.shape == (ball_mesh.n_tets, 4)  # manifold, face-connected


def test_ball_mesh_lies_in_the_label(ball, ball_mesh) -> None:  # noqa: ANN001
    inside = _label_at(ball, ball_mesh.centroids_mm) == 1
    assert inside.mean() >= 0.95
    assert np.linalg.norm(ball_mesh.points_mm, axis=1).max() <= RADIUS_MM + SPACING_MM


def test_size_control(ball) -> None:  # noqa: ANN001
    coarse = meshing.mesh_label_image(ball, [1], 7.0)
    fine = meshing.mesh_label_image(ball, [1], 3.5)
    assert fine.n_tets > 4 * coarse.n_tets  # ~ (7 / 3.5)³ = 8
    for mesh, h in ((coarse, 7.0), (fine, 3.5)):
        assert 0.75 * h < np.median(_edges_mm(mesh)) < 1.35 * h


def test_flipped_direction_gives_the_same_physical_mesh(ball, ball_mesh) -> None:  # noqa: ANN001
    flip = np.diag([-1.0, 1.0, -1.0])
    g = ball.grid
    far = g.index_to_physical(np.array([N_VOX - 1, 0, N_VOX - 1]))  # same voxel centres
    flipped = Image(ball.array[::-1, :, ::-1].copy(),
                    ImageGrid(far, g.spacing_mm, flip, g.size))
    assert np.allclose(np.sort(flipped.grid.voxel_centers_mm()[flipped.array.ravel() == 1], 0),
                       np.sort(g.voxel_centers_mm()[ball.array.ravel() == 1], 0))
    surfaces = [meshing.label_surface(image, 1) for image in (ball, flipped)]
    (va, ta), (vb, tb) = surfaces
    assert np.allclose(np.unique(va.round(6), axis=0), np.unique(vb.round(6), axis=0))
    assert meshing.enclosed_volume_mm3(va, ta) == pytest.approx(meshing.enclosed_volume_mm3(vb, tb))
    mesh = meshing.mesh_label_image(flipped, [1], 4.0)
    assert (mesh.signed_volumes_mm3 > 0).all()
    assert mesh.volumes_mm3.sum() == pytest.approx(ball_mesh.volumes_mm3.sum(), rel=5e-3)
    assert np.allclose(_centre_of_mass(mesh), _centre_of_mass(ball_mesh), atol=0.1)
    assert (_label_at(flipped, mesh.centroids_mm) == 1).mean() >= 0.95


def _centre_of_mass(mesh) -> np.ndarray:  # noqa: ANN001
    v = mesh.volumes_mm3
    return (mesh.centroids_mm * v[:, None]).sum(0) / v.sum()


def test_oblique_direction_and_origin_are_honoured() -> None:
    centre = np.array([30.0, -12.0, 55.0])
    image = _ball_image(_rotation(np.array([1.0, 2.0, 0.5]), 0.6), centre, radius_mm=15.0)
    mesh = meshing.mesh_label_image(image, None, 4.0)
    assert np.allclose(_centre_of_mass(mesh), centre, atol=0.3)
    assert mesh.volumes_mm3.sum() == pytest.approx(4 / 3 * math.pi * 15.0**3, rel=0.03)
    assert (_label_at(image, mesh.centroids_mm) == 1).mean() >= 0.95


def test_cavity_and_island_become_holes_and_separate_solids() -> None:
    image = _ball_image()
    r = np.linalg.norm(image.grid.voxel_centers_mm(), axis=1).reshape(image.grid.shape)
    arr = image.array.copy()
    arr[r <= 10.0] = 0
    arr[r <= 5.0] = 2
    mesh = meshing.mesh_label_image(image.with_array(arr), [1, 2], 4.0)
    shell = mesh.volumes_mm3[mesh.region == 1].sum()
    core = mesh.volumes_mm3[mesh.region == 2].sum()
    assert shell == pytest.approx(4 / 3 * math.pi * (20.0**3 - 10.0**3), rel=0.03)
    assert core == pytest.approx(4 / 3 * math.pi * 5.0**3, rel=0.10)  # 3 voxels radius
    hollow = np.linalg.norm(mesh.centroids_mm[mesh.region == 1], axis=1)
    assert hollow.min() > 8.0  # nothing meshed in the cavity but the island


def test_touching_labels_are_meshed_separately_with_a_warning() -> None:
    image = _ball_image()
    arr = image.array.copy()
    arr[:, :, N_VOX // 2:] *= 2  # two half-balls, touching on a plane
    with pytest.warns(UserWarning, match="do not conform"):
        mesh = meshing.mesh_label_image(image.with_array(arr), None, 4.0)
    for label in (1, 2):
        mask_volume = (arr == label).sum() * SPACING_MM**3
        assert mesh.volumes_mm3[mesh.region == label].sum() == pytest.approx(mask_volume, rel=0.04)


def test_winding_number_and_enclosed_volume_of_a_cube() -> None:
    verts = np.array([[x, y, z] for z in (0, 1) for y in (0, 1) for x in (0, 1)], dtype=float)
    quads = [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]]
    tris = np.array([t for a, b, c, d in quads for t in ([a, b, c], [a, c, d])])
    assert meshing.enclosed_volume_mm3(verts * 2.0, tris) == pytest.approx(8.0)
    assert abs(meshing.winding_number(np.array([0.3, 0.6, 0.5]), verts[tris])) == pytest.approx(1)
    assert meshing.winding_number(np.array([1.3, 0.6, 0.5]), verts[tris]) == pytest.approx(0)


def test_small_specks_are_dropped_with_a_warning(ball) -> None:  # noqa: ANN001
    arr = ball.array.copy()
    arr[1, 1, 1] = 1  # a one-voxel speck, far smaller than a 4 mm tetrahedron
    with pytest.warns(UserWarning, match="dropped 1 surface shell"):
        mesh = meshing.mesh_label_image(ball.with_array(arr), [1], 6.0)
    assert np.linalg.norm(mesh.points_mm, axis=1).max() <= RADIUS_MM + SPACING_MM


def test_bad_inputs_raise_clear_errors(ball) -> None:  # noqa: ANN001
    with pytest.raises(ImageError, match="integer"):
        meshing.mesh_label_image(ball.with_array(ball.array.astype(float)), [1], 4.0)
    with pytest.raises(ImageError, match="label 7"):
        meshing.mesh_label_image(ball, [7], 4.0)
    with pytest.raises(MeshError, match="positive"):
        meshing.mesh_label_image(ball, [1], 0.0)


def test_missing_extra_names_it(ball, monkeypatch) -> None:  # noqa: ANN001
    monkeypatch.setitem(sys.modules, "gmsh", None)
    with pytest.raises(TetdoseError, match=r"tetdose\[meshing\]"):
        meshing.mesh_label_image(ball, [1], 4.0)


def test_cli_mesh_end_to_end(ball, tmp_path) -> None:  # noqa: ANN001
    labels = write_image(tmp_path / "labels.nrrd", ball)
    out = tmp_path / "mesh.vtu"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        code = main(["mesh", "--labels", str(labels), "--label", "1", "--size-mm", "5",
                     "-o", str(out), "-q"])
    assert code == 0
    mesh = read_mesh(out)
    assert (mesh.region == 1).all()
    assert mesh.volumes_mm3.sum() == pytest.approx(4 / 3 * math.pi * RADIUS_MM**3, rel=0.04)
    assert (_label_at(ball, mesh.centroids_mm) == 1).mean() >= 0.95


def test_cli_mesh_bad_label_fails_without_output(ball, tmp_path, capsys) -> None:  # noqa: ANN001
    labels = write_image(tmp_path / "labels.nrrd", ball)
    out = tmp_path / "mesh.vtu"
    code = main(["mesh", "--labels", str(labels), "--label", "9", "-o", str(out)])
    assert code == 2
    assert "label 9" in capsys.readouterr().err
    assert not out.exists()


def _area_mm2(verts: np.ndarray, tris: np.ndarray) -> float:
    p = verts[tris]
    return 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1).sum()


def test_light_smoothing_removes_the_staircase(ball) -> None:  # noqa: ANN001
    sphere_area = 4 * math.pi * RADIUS_MM**2
    raw = meshing.label_surface(ball, 1)
    smooth = meshing.label_surface(ball, 1, smoothing_sigma_vox=1.0)
    raw_excess = _area_mm2(*raw) / sphere_area - 1
    smooth_excess = _area_mm2(*smooth) / sphere_area - 1
    assert abs(smooth_excess) < 0.5 * raw_excess  # staircase facets inflate the raw area
    assert meshing.enclosed_volume_mm3(*raw) == pytest.approx(4 / 3 * math.pi * RADIUS_MM**3,
                                                              rel=0.01)
    # the blur moves a sphere's surface inwards by σ²(κ₁ + κ₂)/2 = σ²/r (module docstring)
    shrunk_mm = RADIUS_MM - (1.0 * SPACING_MM) ** 2 / RADIUS_MM
    assert meshing.enclosed_volume_mm3(*smooth) == pytest.approx(4 / 3 * math.pi * shrunk_mm**3,
                                                                 rel=0.01)


def test_gmsh_timeout_kills_the_child_and_raises(ball) -> None:  # noqa: ANN001
    with pytest.raises(MeshError, match="no answer in 0.01 s"):
        meshing.mesh_label_image(ball, [1], 2.0, timeout_s=0.01)
    assert multiprocessing.active_children() == []


@pytest.mark.slow
def test_wall_thinner_than_the_size_fails_with_a_hint() -> None:
    image = _ball_image()
    r = np.linalg.norm(image.grid.voxel_centers_mm(), axis=1).reshape(image.grid.shape)
    wall = ((r <= RADIUS_MM) & (r >= RADIUS_MM - SPACING_MM)).astype(np.int16)
    with pytest.raises(MeshError, match="smaller target size"):
        meshing.mesh_label_image(image.with_array(wall), [1], 8.0, timeout_s=30)


def test_cli_mesh_gmsh_option(ball, tmp_path) -> None:  # noqa: ANN001
    labels = write_image(tmp_path / "labels.nrrd", ball)
    out = tmp_path / "mesh.vtu"
    assert main(["mesh", "--mesher", "gmsh", "--labels", str(labels), "--size-mm", "6",
                 "--smooth", "0.5", "-o", str(out)]) == 0
    mesh = read_mesh(out)
    assert (mesh.region == 1).all()
    assert mesh.volumes_mm3.sum() == pytest.approx(ball.array.sum() * SPACING_MM**3, rel=0.04)
    checks = (tmp_path / "mesh.checks.json").read_text()
    assert '"mesher": "gmsh"' in checks
