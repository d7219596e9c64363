"""The conforming multi-label mesher (MMG level sets): conformity, volumes, surfaces, quality,
determinism, inputs; skipped without the ``meshing`` extra (mmgpy)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from tetdose.core.image import Image, ImageGrid
from tetdose.core.io import read_mesh, write_image
from tetdose.core.mesh import FACE_VERTICES, TetMesh, signed_volumes_mm3
from tetdose.errors import ImageError, MeshError
from tetdose.meshing import levelset
from tetdose.meshing.distance import signed_distance
from tetdose.meshing.labels import as_label_array, body_mask, default_sizes_mm

pytest.importorskip("mmgpy", reason="mmgpy not installed (extra tetdose[meshing])")

from tetdose.cli import main  # noqa: E402
from tetdose.meshing import conforming_mesh, conformity, dihedral_angles_deg, mesh_checks  # noqa: E402

SPACING_MM = 2.0
#: Nested spheres (1 around 2) and two boxes touching face to face (3 | 4), apart from them.
OUTER_R, INNER_R, INNER_C = 22.0, 9.0, (6.0, 0.0, 0.0)
BOX3 = ((30.0, -12.0, -12.0), (46.0, 12.0, 12.0))
BOX4 = ((45.0, -12.0, -12.0), (62.0, 12.0, 8.0))  # voxel centres x 46…60 touch box 3 (…44)
SIZES = {1: 6.0, 2: 3.0, 3: 5.0, 4: 5.0}


def _scene() -> Image:
    n = np.array([50, 28, 28])
    origin = np.array([-27.0, -27.0, -27.0]) + 0.5 * SPACING_MM
    grid = ImageGrid(origin, (SPACING_MM,) * 3, np.eye(3), tuple(n))
    c = grid.voxel_centers_mm()
    lab = np.zeros(len(c), dtype=np.uint8)
    lab[np.linalg.norm(c, axis=1) <= OUTER_R] = 1
    lab[np.linalg.norm(c - INNER_C, axis=1) <= INNER_R] = 2
    for value, (lo, hi) in ((3, BOX3), (4, BOX4)):
        lab[np.all((c > lo) & (c < hi), axis=1)] = value
    return Image(lab.reshape(grid.shape), grid)


@pytest.fixture(scope="module")
def scene() -> Image:
    return _scene()


@pytest.fixture(scope="module")
def scene_mesh(scene) -> TetMesh:  # noqa: ANN001
    return conforming_mesh(scene, None, SIZES)


@pytest.fixture(scope="module")
def report(scene_mesh, scene) -> dict:  # noqa: ANN001
    return mesh_checks(scene_mesh, scene)


def _faces_between(mesh: TetMesh, a: int, b: int) -> np.ndarray:
    """Triangles (F, 3, 3) [mm] shared by a tet of region a and one of region b."""
    nb = mesh.neighbors
    k, i = np.nonzero(nb >= 0)
    pick = (mesh.region[k] == a) & (mesh.region[nb[k, i]] == b)
    return mesh.points_mm[mesh.tets[k[pick][:, None], FACE_VERTICES[i[pick]]]]


def _area(tri: np.ndarray) -> float:
    return float(0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]),
                                      axis=1).sum())


def test_one_mesh_every_label_a_region(scene_mesh) -> None:  # noqa: ANN001
    assert sorted(np.unique(scene_mesh.region).tolist()) == [1, 2, 3, 4]


def test_conforming_faces_shared_and_surface_closed(scene_mesh) -> None:  # noqa: ANN001
    counts = conformity(scene_mesh)  # neighbors raises if a face had more than two tets
    assert counts["coincident_vertices"] == 0
    assert counts["duplicated_boundary_faces"] == 0
    # The outer surface is closed: every boundary edge is on exactly two boundary triangles.
    faces = scene_mesh.boundary_faces
    edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    _, per_edge = np.unique(edges, axis=0, return_counts=True)
    assert np.all(per_edge == 2)
    # No boundary face inside the outer surface: each boundary triangle's centroid, pushed
    # slightly outwards, lies outside every label.
    tri = scene_mesh.points_mm[faces]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.linalg.norm(normal, axis=1)[:, None]
    probe = tri.mean(axis=1) + 0.8 * SPACING_MM * normal
    scene = _scene()
    idx = np.rint(scene.grid.physical_to_index(probe)).astype(int)
    ok = np.all((idx >= 0) & (idx < np.array(scene.grid.size)), axis=1)
    outside = scene.array[idx[ok, 2], idx[ok, 1], idx[ok, 0]] == 0
    assert outside.mean() > 0.98


def test_interfaces_shared_with_the_analytic_area(scene_mesh) -> None:  # noqa: ANN001
    inner = _area(_faces_between(scene_mesh, 1, 2))
    assert inner == pytest.approx(4 * math.pi * INNER_R**2, rel=0.08)
    touching = _area(_faces_between(scene_mesh, 3, 4))  # the boxes' shared face: voxel faces
    assert touching == pytest.approx(22.0 * 18.0, rel=0.1)  # y −11…11, z −11…7 (rounded rims)
    assert _area(_faces_between(scene_mesh, 4, 3)) == pytest.approx(touching)


def test_volumes_match_voxel_volumes(report) -> None:  # noqa: ANN001
    for lab, e in report["labels"].items():
        limit = 3.0 if e["voxel_volume_cm3"] < 20 else 2.0
        assert abs(e["volume_error_pct"]) < limit, (lab, e)


def test_surfaces_lie_on_the_label_boundaries(report) -> None:  # noqa: ANN001
    for lab, e in report["labels"].items():
        assert e["surface_distance_mean_mm"] < 0.35 * SPACING_MM, (lab, e)
        assert e["surface_distance_p95_mm"] < 0.8 * SPACING_MM, (lab, e)


def test_quality_no_inverted_min_dihedral(scene_mesh, report) -> None:  # noqa: ANN001
    assert report["inverted"] == 0
    assert (scene_mesh.signed_volumes_mm3 > 0).all()
    # MMG leaves a few slivers at the boxes' edges; relocation and flips (quality.py,
    # flips.py) remove them: the 10° holds for every tetrahedron
    angles = dihedral_angles_deg(scene_mesh.points_mm, scene_mesh.tets).min(axis=1)
    assert angles.min() >= 10.0
    assert 40.0 < report["median_dihedral_deg"] < 90.0


def test_surfaces_are_smooth_not_staircase(scene_mesh) -> None:  # noqa: ANN001
    # A voxel staircase has boundary normals along the axes; a smooth sphere has them spread.
    tri = _faces_between(scene_mesh, 1, 2)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n = np.abs(n / np.linalg.norm(n, axis=1)[:, None])
    axis_aligned = (n.max(axis=1) > 0.99).mean()
    assert axis_aligned < 0.2


def test_target_size_per_label(scene_mesh) -> None:  # noqa: ANN001
    p = scene_mesh.points_mm[scene_mesh.tets]
    edges = np.linalg.norm(p[:, [1, 2, 3, 2, 3, 3]] - p[:, [0, 0, 0, 1, 1, 2]], axis=2).mean(axis=1)
    fine = np.median(edges[scene_mesh.region == 2])
    coarse = np.median(edges[scene_mesh.region == 1])
    assert fine < coarse
    assert 0.4 * SIZES[2] < fine < 1.3 * SIZES[2]


def _two_balls(n: int = 20, h: float = 2.0, r_in: float = 6.0, r_out: float = 14.0) -> Image:
    grid = ImageGrid((-(n - 1) * h / 2,) * 3, (h,) * 3, np.eye(3), (n, n, n))
    r = np.linalg.norm(grid.voxel_centers_mm(), axis=1)
    lab = np.where(r <= r_out, 1, 0) + np.where(r <= r_in, 1, 0)
    return Image(lab.reshape(grid.shape).astype(np.uint8), grid)


def test_thin_shell_two_voxels_thick_is_kept() -> None:
    # Label 2: a shell two voxels (4 mm) thick around the ball of label 1.
    img = _two_balls(r_in=10.0, r_out=10.0 + 2 * 2.0)
    img = img.with_array(np.where(img.array == 2, 1, np.where(img.array == 1, 2, 0)))
    a = conforming_mesh(img, None, {1: 4.0, 2: 3.0})
    e = mesh_checks(a, img)["labels"]["2"]
    assert e["tets"] > 0
    assert abs(e["volume_error_pct"]) < 3.0
    # The shell surrounds label 1: (almost) no face of 1 is on the outer surface.
    k, i = np.nonzero(a.neighbors < 0)
    tri = a.points_mm[a.tets[k[:, None], FACE_VERTICES[i]]]
    assert _area(tri[a.region[k] == 1]) < 0.005 * _area(tri)


def test_same_input_same_mesh() -> None:
    img = _two_balls()
    a, b = (conforming_mesh(img, None, {1: 6.0, 2: 3.0}) for _ in range(2))
    np.testing.assert_array_equal(a.points_mm, b.points_mm)
    np.testing.assert_array_equal(a.tets, b.tets)
    np.testing.assert_array_equal(a.region, b.region)


def test_tets_below_the_required_angle_are_warned(monkeypatch) -> None:  # noqa: ANN001
    """A mesh whose smallest angle misses the requirement is not silent: the warning names the
    labels and the fix (the requirement raised above any real angle forces the case)."""
    from tetdose.meshing import checks, mmg

    monkeypatch.setattr(mmg, "REQUIRED_DIHEDRAL_DEG", 89.0)
    with pytest.warns(UserWarning, match=r"label\(s\) \[1, 2\] stay below 89°.*--size-mm"):
        mesh = conforming_mesh(_two_balls(), None, {1: 6.0, 2: 3.0})
    assert checks.dihedral_angles_deg(mesh.points_mm, mesh.tets).min() >= 10.0  # as required


def test_flipped_direction_meshes_in_patient_coordinates(scene) -> None:  # noqa: ANN001
    # The same voxels stored with a y-flipped direction: same physical mesh volume per label.
    g = scene.grid
    direction = np.diag([1.0, -1.0, 1.0])
    origin = g.origin_mm + np.array([0.0, (g.size[1] - 1) * g.spacing_mm[1], 0.0])
    flipped = Image(scene.array[:, ::-1, :], ImageGrid(origin, g.spacing_mm, direction, g.size))
    mesh = conforming_mesh(flipped, [2], 4.0)
    volume = mesh.volumes_mm3.sum()
    assert volume == pytest.approx(np.count_nonzero(scene.array == 2) * SPACING_MM**3, rel=0.03)
    centre = (mesh.centroids_mm * mesh.volumes_mm3[:, None]).sum(axis=0) / volume
    np.testing.assert_allclose(centre, INNER_C, atol=0.5)


def test_fraction_below_matches_sampling() -> None:
    rng = np.random.default_rng(4)
    values = rng.normal(size=(40, 4))
    values[0] = [0.3, 0.3, 0.3, 1.0]  # tied knots
    # Uniform points in the reference tetrahedron (Dirichlet(1,1,1,1) barycentrics).
    bary = rng.dirichlet(np.ones(4), size=200_000)
    for t in (-0.5, 0.1, 0.3, 0.8):
        exact = levelset.fraction_below(values, t)
        sampled = ((bary @ values.T) < t).mean(axis=0)
        np.testing.assert_allclose(exact, sampled, atol=4e-3)


def test_volume_shift_recovers_a_plane_offset() -> None:
    # f = x − 0.2 on a unit-cube mesh: {f < δ} has volume 0.2 + δ; ask for 0.5 → δ = 0.3.
    from tetdose.core import tetgrid

    pts = tetgrid.grid_nodes(np.zeros(3), np.full(3, 0.25), (4, 4, 4))
    tets = tetgrid.grid_tets((4, 4, 4))
    vols = np.abs(signed_volumes_mm3(pts, tets))
    f = (pts[:, 0] - 0.2)[tets]
    assert levelset.volume_shift(f, vols, 0.5, 0.1) == pytest.approx(0.3, abs=1e-4)


def test_distance_field_is_zero_on_voxel_faces() -> None:
    grid = ImageGrid((0.0, 0.0, 0.0), (1.0, 2.0, 3.0), np.eye(3), (12, 10, 8))
    mask = np.zeros(grid.shape, dtype=bool)
    mask[2:6, 3:7, 4:9] = True  # i 4…8, j 3…6, k 2…5
    phi = signed_distance(mask, grid)
    face = np.array([[8.5 * 1.0, 4.5 * 2.0, 3.5 * 3.0], [6.0, 2.5 * 2.0, 3.5 * 3.0]])
    np.testing.assert_allclose(phi(face), 0.0, atol=1e-9)
    assert phi(np.array([[6.0, 9.0, 10.5]]))[0] < 0 < phi(np.array([[11.0, 9.0, 10.5]]))[0]


def test_ct_refused_as_labels_quickly(tmp_path, capsys) -> None:  # noqa: ANN001
    grid = ImageGrid((0.0,) * 3, (1.0,) * 3, np.eye(3), (40, 40, 40))
    ct = np.random.default_rng(0).integers(-1000, 1500, size=grid.shape).astype(np.int16)
    with pytest.raises(ImageError, match="looks like a CT"):
        as_label_array(ct)
    with pytest.raises(ImageError, match="more than"):
        as_label_array(np.arange(grid.n_voxels).reshape(grid.shape))
    path = write_image(tmp_path / "ct.nrrd", Image(ct, grid))
    assert main(["mesh", "--labels", str(path), "-o", str(tmp_path / "m.vtu")]) == 2
    assert "--ct" in capsys.readouterr().err
    assert not (tmp_path / "m.vtu").exists()


def test_default_sizes_follow_size_and_thickness() -> None:
    sizes = default_sizes_mm({1: 4 / 3 * math.pi * 12.5**3, 2: 2e6, 3: 3e4},
                             {1: 12.5, 2: 60.0, 3: 1.5}, np.array([1.0, 1.0, 2.0]))
    assert sizes[1] == pytest.approx(25.0 / 8.0)
    assert sizes[2] == 12.0
    assert sizes[3] == pytest.approx(3.0)  # thickness-limited


def test_body_mask_fills_lungs_and_drops_the_couch() -> None:
    z, y, x = np.mgrid[:20, :60, :60]
    ct = np.full((20, 60, 60), -1000, dtype=np.int16)
    body = (x - 30) ** 2 / 25**2 + (y - 28) ** 2 / 18**2 <= 1
    ct[body] = 40
    ct[body & ((x - 22) ** 2 + (y - 28) ** 2 <= 36)] = -850  # a lung: a hole in every slice
    ct[:, 55:58, 10:50] = 200  # a couch, not connected
    mask = body_mask(ct)
    np.testing.assert_array_equal(mask, body)


def test_cli_mesh_writes_mesh_and_checks(tmp_path, capsys) -> None:  # noqa: ANN001
    labels = write_image(tmp_path / "lab.nii.gz", _two_balls())
    out = tmp_path / "m.vtu"
    assert main(["mesh", "--labels", str(labels), "--size-mm", "1=6,2=3", "-o", str(out)]) == 0
    mesh = read_mesh(out)
    assert sorted(np.unique(mesh.region).tolist()) == [1, 2]
    checks = json.loads((tmp_path / "m.checks.json").read_text())
    assert set(checks["labels"]) == {"1", "2"}
    assert checks["conformity"]["coincident_vertices"] == 0
    assert checks["n_tets"] == mesh.n_tets
    printed = capsys.readouterr().out
    assert "interface faces" in printed and "checks →" in printed
    assert np.mean(dihedral_angles_deg(mesh.points_mm, mesh.tets).min(axis=1) < 10.0) < 5e-3


def test_missing_label_and_bad_size_errors(scene) -> None:  # noqa: ANN001
    with pytest.raises(ImageError, match="no voxel carries label 9"):
        conforming_mesh(scene, [9])
    with pytest.raises(MeshError, match="positive"):
        conforming_mesh(scene, [2], {2: -1.0})


def test_cli_mesh_rtstruct_rois_inside_the_auto_body(tmp_path) -> None:  # noqa: ANN001
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from test_rtstruct import CENTRE, R_MM, make_grid, sphere_and_ring, write_rtstruct

    grid = make_grid(np.eye(3))
    p = grid.voxel_centers_mm() - CENTRE
    hu = np.where((p[:, 0] / 19.0) ** 2 + (p[:, 1] / 19.0) ** 2 <= 1.0, 40, -1000)
    ct = write_image(tmp_path / "ct.nrrd", Image(hu.reshape(grid.shape).astype(np.int16), grid))
    rs = write_rtstruct(tmp_path / "rs.dcm", sphere_and_ring(grid))
    out = tmp_path / "body.vtu"
    assert main(["mesh", "--structures", str(rs), "--roi", "Sphere", "--ct", str(ct),
                 "--body", "auto", "--size-mm", "1=4,2=5", "-o", str(out)]) == 0
    mesh = read_mesh(out)
    checks = json.loads((tmp_path / "body.checks.json").read_text())
    assert checks["names"] == {"1": "Sphere", "2": "body"}
    assert sorted(np.unique(mesh.region).tolist()) == [1, 2]
    sphere = mesh.volumes_mm3[mesh.region == 1].sum()
    assert sphere == pytest.approx(checks["labels"]["1"]["voxel_volume_cm3"] * 1000, rel=0.03)
    assert sphere == pytest.approx(4 / 3 * math.pi * R_MM**3, rel=0.06)
    assert checks["conformity"]["interface_faces"] > 0
