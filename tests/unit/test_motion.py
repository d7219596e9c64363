"""Unit tests of tetdose.motion: phases, DVF, surfaces/ICP, FEM, breathing, CLI."""

from __future__ import annotations

import itertools
import sys
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from tetdose.core.image import Image, ImageGrid
from tetdose.core.mesh import TetMesh
from tetdose.errors import GeometryMismatchError, MeshError, TetdoseError, TopologyMismatchError
from tetdose.motion.breathing import BreathingModel
from tetdose.motion.dvf import DisplacementField, read_dvf, warp_image, write_dvf
from tetdose.motion.fem import (
    boundary_surface,
    propagate_boundary,
    solve_linear_elastic,
    surface_driven_points,
)
from tetdose.motion.phases import PVD_NAME, PhaseSeries
from tetdose.motion.surface import closest_point_on_triangles, closest_points, icp


def box_mesh(n=(3, 3, 3), size_mm=(30.0, 24.0, 18.0), origin_mm=(0.0, 0.0, 0.0)) -> TetMesh:
    """A box split into cubes of six Kuhn tetrahedra each (conforming), positively oriented."""
    nx, ny, nz = n
    axes = [np.linspace(o, o + s, k + 1) for o, s, k in zip(origin_mm, size_mm, n, strict=True)]
    z, y, x = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    pts = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)

    def vid(i, j, k):
        return (k * (ny + 1) + j) * (nx + 1) + i

    tets = []
    for i, j, k in itertools.product(range(nx), range(ny), range(nz)):
        for perm in itertools.permutations(range(3)):
            c = np.array([i, j, k])
            ids = [vid(*c)]
            for a in perm:
                c = c.copy()
                c[a] += 1
                ids.append(vid(*c))
            tets.append(ids)
    mesh = TetMesh(pts, np.array(tets)).with_fixed_orientation()
    rho = 1.0 + 0.3 * np.sin(pts[:, 0] / 7.0) + 0.02 * pts[:, 2] + 0.01 * pts[:, 1]
    return mesh.with_data(point_data={"density": rho})


def rotation(axis, angle_rad) -> np.ndarray:
    axis = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle_rad) * k + (1 - np.cos(angle_rad)) * k @ k


# --- phases -----------------------------------------------------------------------------------


def test_topology_mismatch_names_first_cell():
    ref = box_mesh()
    tets = ref.tets.copy()
    tets[[7, 9]] = tets[[9, 7]]
    other = TetMesh(ref.points_mm, tets)
    with pytest.raises(TopologyMismatchError, match=r"phase 1: tetrahedron 7 differs"):
        PhaseSeries.from_meshes(ref, [ref, other])


def test_inverted_cells_name_phase_and_ids():
    ref = box_mesh()
    pts = ref.points_mm.copy()
    v = ref.tets[5, 0]
    pts[v] = 2 * ref.points_mm[ref.tets[5, 1:]].mean(axis=0) - pts[v]  # mirror through the face
    with pytest.raises(MeshError, match=r"phase 1 \(50 %\).*ids \[.*\b5\b"):
        PhaseSeries(ref, np.stack([ref.points_mm, pts]))


def test_write_read_pvd_round_trip(tmp_path):
    ref = box_mesh()
    pts = np.stack([ref.points_mm, ref.points_mm + [0.0, 0.0, -2.0]])
    rho = np.stack([ref.point_data["density"], 0.9 * ref.point_data["density"]])
    series = PhaseSeries(ref, pts, [0.0, 50.0], [0.25, 0.75], rho)
    paths = series.write(tmp_path / "phases")
    root = ET.parse(tmp_path / "phases" / PVD_NAME).getroot()
    listed = [d.attrib["file"] for d in root.iter("DataSet")]
    assert root.attrib["type"] == "Collection"
    assert listed == [p.name for p in paths] and all(p.exists() for p in paths)
    back = PhaseSeries.read(None, tmp_path / "phases")
    np.testing.assert_array_equal(back.points_mm, pts)
    np.testing.assert_allclose(back.density_g_cm3, rho, rtol=1e-15)
    np.testing.assert_array_equal(back.phase_percent, [0.0, 50.0])
    np.testing.assert_allclose(back.time_weight, [0.25, 0.75])


# --- DVF --------------------------------------------------------------------------------------


def affine_field(grid: ImageGrid, a: np.ndarray, b: np.ndarray) -> DisplacementField:
    centres = grid.voxel_centers_mm()
    return DisplacementField((centres @ a.T + b).reshape(*grid.shape, 3), grid)


def test_dvf_affine_field_is_exact_and_matches_sitk():
    import SimpleITK as sitk

    rng = np.random.default_rng(3)
    grid = ImageGrid([-20.0, -25.0, -15.0], [2.0, 2.5, 3.0], rotation([1, -1, 2], 0.4),
                     (30, 26, 18))
    a, b = 0.05 * rng.standard_normal((3, 3)), np.array([1.5, -2.0, 4.0])
    field = affine_field(grid, a, b)
    idx = rng.uniform(0, 1, (200, 3)) * (np.array(grid.size) - 1)
    pts = grid.index_to_physical(idx)
    np.testing.assert_allclose(field.moved(pts), pts + pts @ a.T + b, atol=1e-10)
    tr = sitk.DisplacementFieldTransform(field.to_sitk())
    ref = np.array([tr.TransformPoint(tuple(p)) for p in pts[:20]])
    np.testing.assert_allclose(field.moved(pts[:20]), ref, atol=1e-9)


def test_dvf_identity_and_file_round_trip(tmp_path):
    mesh = box_mesh()
    grid = ImageGrid([-5.0, -5.0, -5.0], [2.0, 2.0, 2.0], np.eye(3), (22, 19, 16))
    zero = DisplacementField(np.zeros((*grid.shape, 3)), grid)
    np.testing.assert_array_equal(zero.moved(mesh.points_mm), mesh.points_mm)
    field = affine_field(grid, np.diag([0.01, 0.02, -0.03]), np.array([1.0, 0.0, 2.0]))
    back = read_dvf(write_dvf(tmp_path / "dvf.nrrd", field))
    np.testing.assert_array_equal(back.vectors_mm, field.vectors_mm)
    assert back.grid.same_as(grid)


def test_dvf_not_covering_mesh_is_refused():
    mesh = box_mesh()
    grid = ImageGrid([0.0, 0.0, 0.0], [2.0, 2.0, 2.0], np.eye(3), (10, 13, 10))  # x up to 18 mm
    field = DisplacementField(np.zeros((*grid.shape, 3)), grid)
    n_out = int((mesh.points_mm[:, 0] > 18.0).sum())
    with pytest.raises(GeometryMismatchError, match=rf"does not cover {n_out} of 64 mesh"):
        field.moved(mesh.points_mm)


def test_warp_image_translation():
    grid = ImageGrid([0.0, 0.0, 0.0], [1.0, 1.0, 1.0], np.eye(3), (20, 16, 12))
    k, j, i = np.meshgrid(*(np.arange(n) for n in grid.shape), indexing="ij")
    img = Image((3.0 * i + 2.0 * j - k).astype(np.float64), grid)
    shift = np.array([2.0, -1.0, 1.0])  # reference → phase
    field = DisplacementField(np.broadcast_to(shift, (*grid.shape, 3)).copy(), grid)
    out = warp_image(img, field, outside_value=-1000.0)
    expect = img.array - (3.0 * shift[0] + 2.0 * shift[1] - shift[2])  # I_t(x) = I_0(x − shift)
    inner = (slice(3, -3), slice(3, -3), slice(3, -3))
    np.testing.assert_allclose(out.array[inner], expect[inner], atol=1e-2)


def test_dvf_inverse_is_consistent_with_the_forward_map():
    grid = ImageGrid([0.0, 0.0, 0.0], [2.0, 2.0, 2.0], np.eye(3), (30, 30, 30))
    c = grid.voxel_centers_mm()
    u = np.stack([2.0 * np.sin(c[:, 1] / 15.0), 1.5 * np.cos(c[:, 2] / 12.0),
                  -3.0 * np.sin(c[:, 0] / 20.0)], axis=1)
    field = DisplacementField(u.reshape(*grid.shape, 3), grid)
    inv = field.inverse()
    p = np.random.default_rng(5).uniform(12.0, 46.0, (200, 3))
    np.testing.assert_allclose(inv.at(field.moved(p)), -field.at(p), atol=0.02)


# --- surfaces and ICP -------------------------------------------------------------------------


def test_closest_point_on_triangle_against_dense_sampling():
    rng = np.random.default_rng(0)
    tri = rng.standard_normal((3, 3))
    p = 2.0 * rng.standard_normal((300, 3))
    cp = closest_point_on_triangles(p, *(np.broadcast_to(v, p.shape) for v in tri))
    u, v = np.meshgrid(np.linspace(0, 1, 201), np.linspace(0, 1, 201))
    keep = u + v <= 1
    samples = tri[0] + np.outer(u[keep], tri[1] - tri[0]) + np.outer(v[keep], tri[2] - tri[0])
    d_sampled = np.sqrt(((p[:, None] - samples[None]) ** 2).sum(axis=2)).min(axis=1)
    d = np.linalg.norm(cp - p, axis=1)
    assert np.all(d <= d_sampled + 1e-12)
    assert np.all(d >= d_sampled - 0.02)
    lam = np.linalg.lstsq(np.stack([tri[1] - tri[0], tri[2] - tri[0]], 1), (cp - tri[0]).T,
                          rcond=None)[0]
    assert np.all(lam >= -1e-9) and np.all(lam.sum(axis=0) <= 1 + 1e-9)  # on the triangle


def test_closest_points_on_surface_is_the_minimum_over_triangles():
    surf, _ = boundary_surface(box_mesh())
    q = np.random.default_rng(1).uniform(-10, 40, (100, 3))
    cp, dist = closest_points(q, surf)
    tri = surf.vertices_mm[surf.triangles]
    brute = np.full(len(q), np.inf)
    for t in tri:
        c = closest_point_on_triangles(q, *(np.broadcast_to(v, q.shape) for v in t))
        brute = np.minimum(brute, np.linalg.norm(c - q, axis=1))
    np.testing.assert_allclose(dist, brute, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(cp - q, axis=1), dist, atol=1e-12)


def test_icp_recovers_known_rigid_transform():
    mesh = box_mesh()
    pts = mesh.points_mm.copy()
    pts[:, 0] += 0.1 * pts[:, 1] ** 1.5  # break the box's symmetries
    surf, _ = boundary_surface(mesh.moved(pts))
    r, t = rotation([0.3, -0.5, 1.0], np.radians(12.0)), np.array([4.0, -7.0, 2.5])
    result = icp(surf, surf.transformed(r, t))
    np.testing.assert_allclose(result.rotation, r, atol=1e-7)
    np.testing.assert_allclose(result.translation_mm, t, atol=1e-6)
    assert result.rms_mm < 1e-6


# --- FEM --------------------------------------------------------------------------------------


def test_fem_translation_of_surface_translates_the_inside():
    mesh = box_mesh()
    surf, _ = boundary_surface(mesh)
    shift = np.array([3.0, -2.0, 5.0])
    moved = surface_driven_points(mesh, surf.transformed(np.eye(3), shift), n_increments=2)
    np.testing.assert_allclose(moved, mesh.points_mm + shift, atol=1e-8)


def test_fem_boundary_lands_on_a_stretched_target_surface():
    mesh = box_mesh()
    surf, ids = boundary_surface(mesh)
    target = surf.transformed(np.diag([1.0, 1.0, 1.15]), [0.0, 0.0, 0.0])
    pts = surface_driven_points(mesh, target, n_increments=3)
    _, dist = closest_points(pts[ids], target)
    assert dist.max() < 1e-9  # every boundary vertex on the target (closest-point matching)
    mesh.moved(pts).check_cells()


def test_fem_uniaxial_stretch_matches_analytic_field():
    """Bar stretched along x with symmetry planes x=0, y=0, z=0 and free lateral faces.

    Linear elasticity: u = (δ x/L, −ν δ y/L, −ν δ z/L) exactly (uniform uniaxial stress); P1
    holds linear fields, so the FEM must reproduce it to solver round-off.
    """
    mesh = box_mesh(n=(4, 2, 2), size_mm=(40.0, 10.0, 10.0))
    p, nu, delta = mesh.points_mm, 0.45, 0.4
    fixed = np.zeros((mesh.n_points, 3), dtype=bool)
    values = np.zeros((mesh.n_points, 3))
    fixed[np.isclose(p[:, 0], 0.0), 0] = True
    end = np.isclose(p[:, 0], 40.0)
    fixed[end, 0], values[end, 0] = True, delta
    fixed[np.isclose(p[:, 1], 0.0), 1] = True
    fixed[np.isclose(p[:, 2], 0.0), 2] = True
    u = solve_linear_elastic(p, mesh.tets, fixed, values, poisson=nu)
    strain = delta / 40.0
    expect = np.stack([strain * p[:, 0], -nu * strain * p[:, 1], -nu * strain * p[:, 2]], 1)
    np.testing.assert_allclose(u, expect, atol=1e-9)


def test_fem_increments_reproduce_affine_boundary_map():
    mesh = box_mesh()
    _, ids = boundary_surface(mesh)
    f = np.array([[1.2, 0.1, 0.0], [0.0, 0.9, 0.05], [0.02, 0.0, 1.1]])
    target = mesh.points_mm @ f.T + [1.0, 2.0, 3.0]
    pts = propagate_boundary(mesh, ids, (target - mesh.points_mm)[ids], n_increments=3)
    np.testing.assert_allclose(pts, target, atol=1e-9)


def test_missing_scikit_fem_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "skfem", None)
    mesh = box_mesh()
    with pytest.raises(TetdoseError, match=r"tetdose\[fem\]"):
        solve_linear_elastic(mesh.points_mm, mesh.tets, np.ones((mesh.n_points, 3), bool),
                             np.zeros((mesh.n_points, 3)))


# --- breathing --------------------------------------------------------------------------------


def test_breathing_cycle_and_field():
    model = BreathingModel(amplitude_mm=6.0, period_s=5.0, n=2)
    assert model.cycle(0.0) == pytest.approx(1.0) and model.cycle(2.5) == pytest.approx(0.0)
    t = np.linspace(0, 5, 7)
    np.testing.assert_allclose(model.cycle(t), np.cos(np.pi * t / 5.0) ** 4)
    mesh = box_mesh(size_mm=(60.0, 50.0, 120.0))
    series = model.series(mesh, 10)
    np.testing.assert_allclose(series.points_mm[5], mesh.points_mm, atol=1e-12)  # end-exhale
    u = series.points_mm[0] - mesh.points_mm  # end-inhale
    bottom = np.isclose(mesh.points_mm[:, 2], 0.0)
    np.testing.assert_allclose(u[bottom, 2], -6.0)  # full amplitude at the diaphragm, downwards
    np.testing.assert_allclose(u[np.isclose(mesh.points_mm[:, 2], 120.0)], 0.0)  # still apex
    assert np.abs(u[:, :2]).max() < 0.5 * np.abs(u[:, 2]).max()
    vol = np.array([mesh.moved(p).volumes_mm3.sum() for p in series.points_mm])
    # No lung: tissue keeps its volume (det of the continuous map is 1; tets to curvature).
    np.testing.assert_allclose(vol / mesh.volumes_mm3.sum(), 1.0, atol=2e-3)
    lung = model.series(mesh, 10, lung_regions=[0])  # the whole (unlabelled) mesh as lung
    vol = [mesh.moved(p).volumes_mm3.sum() for p in lung.points_mm]
    assert vol[0] > vol[2] > vol[5] == pytest.approx(mesh.volumes_mm3.sum())  # inhale expands


def _label_density(phantom) -> np.ndarray:
    """Vertex density [g/cm³]: 0.26 in lung tets, 1.0 elsewhere (averaged at shared vertices)."""
    mesh = phantom.mesh
    lung = [k for k, v in phantom.materials.items() if v == "lung"]
    rho_tet = np.where(np.isin(mesh.region, lung), 0.26, 1.0)
    total = np.bincount(mesh.tets.ravel(), np.repeat(rho_tet, 4), mesh.n_points)
    return total / np.bincount(mesh.tets.ravel(), minlength=mesh.n_points)


def _volumes(phantom, amplitude_mm=10.0):
    from tetdose.motion.conserve import region_volumes

    mesh = phantom.mesh
    series = BreathingModel(amplitude_mm).series(mesh, 4, density_g_cm3=_label_density(phantom))
    return {r.region: r for r in region_volumes(mesh, mesh.moved(series.points_mm[0]))}


def test_breathing_keeps_liver_volume():
    """Issue 27: the liver phantom grew 16 % (tets up to 36 %); liver is incompressible."""
    from tetdose.phantoms import make_phantom

    mesh = make_phantom("liver", size="small").mesh
    series = BreathingModel(10.0).series(mesh, 4, density_g_cm3=np.ones(mesh.n_points))
    rel = mesh.moved(series.points_mm[0]).volumes_mm3 / mesh.volumes_mm3 - 1.0  # end-inhale
    assert abs(mesh.moved(series.points_mm[0]).volumes_mm3.sum() / mesh.volumes_mm3.sum() - 1) < 5e-3
    assert np.percentile(np.abs(rel), 99) < 0.04  # the motion's curvature across a tet
    assert np.abs(rel).max() < 0.2  # the worst: flat tets on the staircase surface
    assert np.abs(series.points_mm[0] - mesh.points_mm).max() > 9.0  # it does move


def test_breathing_changes_lung_volume_only():
    """Thorax: every non-lung region keeps its volume (≤ 2 %); a free lung (the lung phantom's
    mesh is lung and vessels) grows on inhale by the model's expansion."""
    from tetdose.phantoms import make_phantom

    thorax = make_phantom("thorax", size="small")
    for label, r in _volumes(thorax).items():
        if thorax.materials[label] not in ("lung", "blood"):  # vessels sit inside the lung
            assert abs(r.total) < 0.02, (thorax.label_names[label], r)
            assert abs(r.median) < 0.01
    lung = _volumes(make_phantom("lung", size="small"))[2]
    assert 0.05 < lung.total < 0.2 and lung.min > 0.0


def test_breathing_lung_regions_are_checked():
    with pytest.raises(TetdoseError, match=r"lung region\(s\) \[9\] not in the mesh"):
        BreathingModel().series(box_mesh(), 2, lung_regions=[9])


# --- CLI --------------------------------------------------------------------------------------


def read_report(path) -> np.ndarray:
    return np.genfromtxt(path, delimiter=",", names=True)


def test_cli_deform_breathing_and_4dct(tmp_path):
    from tetdose.cli import main
    from tetdose.core.calibration import HUCalibration
    from tetdose.core.io import read_image, write_image, write_mesh

    mesh = box_mesh(origin_mm=(10.0, 10.0, 10.0))
    write_mesh(tmp_path / "mapped.vtu", mesh)
    out = tmp_path / "phases"
    assert main(["deform", "--mesh", str(tmp_path / "mapped.vtu"), "--breathing",
                 "--amplitude-mm", "4", "--n-phases", "4", "-o", str(out)]) == 0
    report = read_report(out / "mass_report.csv")
    ref_mass = float(np.dot(np.bincount(mesh.tets.ravel(), np.repeat(mesh.volumes_mm3 / 4, 4)),
                            mesh.point_data["density"])) / 1000.0
    np.testing.assert_allclose(report["total_mass_g"], ref_mass, rtol=1e-12)
    np.testing.assert_array_equal(report["phase_percent"], [0.0, 25.0, 50.0, 75.0])
    volumes = read_report(out / "volume_report.csv")  # ΔV/V per phase and region
    np.testing.assert_array_equal(volumes["phase_percent"], [0.0, 25.0, 50.0, 75.0])
    assert np.all(np.abs(volumes["volume_change_total"]) < 5e-3)  # no lung: volume kept
    assert np.all(volumes["volume_change_min"] <= volumes["volume_change_median"])
    series = PhaseSeries.read(None, out)
    assert series.n_phases == 4 and series.density_g_cm3 is not None
    assert np.abs(series.points_mm[0] - mesh.points_mm).max() == pytest.approx(4.0)

    grid = ImageGrid([0.0, 0.0, 0.0], [4.0, 4.0, 4.0], np.eye(3), (14, 13, 11))
    ct = Image(np.full(grid.shape, -300, dtype=np.int16), grid)
    write_image(tmp_path / "ct.nrrd", ct)
    ct4d = tmp_path / "ct4d"
    assert main(["4dct", "-q", "--phases", str(out), "--like", str(tmp_path / "ct.nrrd"),
                 "-o", str(ct4d), "--format", "nrrd", "--background", "air"]) == 0
    files = sorted(ct4d.glob("*.nrrd"))
    assert len(files) == 4
    cal = HUCalibration.schneider2000()
    for f in files:
        img = read_image(f)
        assert img.grid.same_as(grid)
        mass_g = cal.density(img.array).sum() * grid.voxel_volume_mm3 / 1000.0
        vol_mm3 = grid.n_voxels * grid.voxel_volume_mm3
        air_g = 0.00120479 * (vol_mm3 - mesh.volumes_mm3.sum()) / 1000.0  # mesh volume differs
        assert abs(mass_g - air_g - ref_mass) < 0.01 * ref_mass  # per phase; 1 HU rounding
    assert main(["4dct", "-q", "--phases", str(out), "--like", str(tmp_path / "ct.nrrd"),
                 "-o", str(tmp_path / "dcm"), "--format", "dicom"]) == 0
    first_nrrd = tmp_path / "n0"
    assert main(["4dct", "-q", "--phases", str(out), "--like", str(tmp_path / "ct.nrrd"),
                 "-o", str(first_nrrd), "--format", "nrrd"]) == 0
    folders = sorted(p for p in (tmp_path / "dcm").iterdir() if p.is_dir())
    assert [p.name for p in folders] == ["phase_000", "phase_025", "phase_050", "phase_075"]
    for folder, f in zip(folders, sorted(first_nrrd.glob("*.nrrd")), strict=True):
        a, b = read_image(folder), read_image(f)
        assert a.grid.same_as(b.grid)
        assert np.abs(a.array.astype(float) - b.array).max() <= 1.0
    outside = read_image(f).array[0, 0, 0]  # background "ct" kept the reference CT there
    assert outside == pytest.approx(cal.hu_of(cal.density(-300.0)), abs=0.5)


def test_cli_deform_dvf_and_surfaces(tmp_path):
    import meshio

    from tetdose.cli import main
    from tetdose.core.io import write_mesh

    mesh = box_mesh()
    write_mesh(tmp_path / "mapped.vtu", mesh)
    grid = ImageGrid([-8.0, -8.0, -8.0], [2.0, 2.0, 2.0], np.eye(3), (25, 22, 19))
    f = np.diag([0.05, -0.02, 0.03])
    write_dvf(tmp_path / "dvf.nrrd", affine_field(grid, f, np.array([1.0, 0.0, -1.0])))
    assert main(["deform", "--mesh", str(tmp_path / "mapped.vtu"), "--dvf",
                 str(tmp_path / "dvf.nrrd"), "-o", str(tmp_path / "d")]) == 0
    got = PhaseSeries.read(None, tmp_path / "d")
    expect = mesh.points_mm + mesh.points_mm @ f.T + [1.0, 0.0, -1.0]
    np.testing.assert_allclose(got.points_mm[0], expect, atol=1e-10)
    np.testing.assert_allclose(got.density_g_cm3[0], mesh.point_data["density"] / np.prod(
        1 + np.diag(f)), rtol=1e-10)  # uniform stretch: ρ/det F

    surf, _ = boundary_surface(mesh)
    shifted = surf.transformed(np.eye(3), [0.0, 0.0, 3.0])
    meshio.write(tmp_path / "s.stl", meshio.Mesh(shifted.vertices_mm,
                                                 [("triangle", shifted.triangles)]), binary=True)
    assert main(["deform", "--mesh", str(tmp_path / "mapped.vtu"), "--surfaces",
                 str(tmp_path / "s.stl"), "-o", str(tmp_path / "s")]) == 0
    got = PhaseSeries.read(None, tmp_path / "s")
    np.testing.assert_allclose(got.points_mm[0], mesh.points_mm + [0, 0, 3.0], atol=1e-5)
    np.testing.assert_allclose(got.density_g_cm3[0], mesh.point_data["density"], rtol=1e-9)


def test_virtual_4dct_warps_the_outside_with_the_dvf():
    from tetdose.motion.conserve import update_series
    from tetdose.motion.ct4d import virtual_4dct

    grid = ImageGrid([-20.0, -20.0, -20.0], [2.0, 2.0, 2.0], np.eye(3), (40, 30, 30))
    i = np.arange(40)
    ct = Image(np.broadcast_to(-800.0 + 10.0 * i, grid.shape).copy(), grid)  # linear HU in x
    shift = np.array([4.0, 0.0, 0.0])  # two voxels along x, reference → phase
    field = DisplacementField(np.broadcast_to(shift, (*grid.shape, 3)).copy(), grid)
    mesh = box_mesh(n=(2, 2, 2), size_mm=(8.0, 8.0, 8.0))
    series = PhaseSeries(mesh, np.stack([mesh.points_mm, field.moved(mesh.points_mm)]), [0, 50])
    series, _ = update_series(series)
    still, moved = virtual_4dct(series, ct, dvfs=[DisplacementField(0 * field.vectors_mm, grid),
                                                  field])
    far = (slice(0, 5), slice(0, 5), slice(5, 30))  # away from the mesh and the borders
    np.testing.assert_allclose(still.array[far], ct.array[far], atol=0.51)
    np.testing.assert_allclose(moved.array[far], ct.array[far] - 20.0, atol=0.51)
    # the mesh moved with the DVF: its voxels are the reference phase's, two voxels further on
    np.testing.assert_array_equal(moved.array[10:14, 10:14, 12:16], still.array[10:14, 10:14,
                                                                                 10:14])


def test_cli_deform_dvfs_pair_with_phases_by_their_names(tmp_path):
    """Issue 27 probe: `deform --dvf phase_050.0.nrrd phase_000.0.nrrd` took argument order for
    phase order (and 0 %, 50 % for the two); the names say the phases."""
    from tetdose.cli import main
    from tetdose.core.io import write_mesh

    mesh = box_mesh(origin_mm=(10.0, 10.0, 10.0))
    write_mesh(tmp_path / "mapped.vtu", mesh)
    grid = ImageGrid([0.0, 0.0, 0.0], [4.0, 4.0, 4.0], np.eye(3), (14, 13, 11))
    shift = {0.0: 0.0, 50.0: 2.0, 75.0: 3.0}  # mm along x, per phase percent
    files = {p: write_dvf(tmp_path / f"phase_{p:05.1f}.nrrd", DisplacementField(
        np.broadcast_to([s, 0.0, 0.0], (*grid.shape, 3)).copy(), grid)) for p, s in shift.items()}
    out = tmp_path / "phases"
    assert main(["deform", "-q", "--mesh", str(tmp_path / "mapped.vtu"), "--dvf",
                 str(files[75.0]), str(files[0.0]), str(files[50.0]), "-o", str(out)]) == 0
    series = PhaseSeries.read(None, out)
    np.testing.assert_array_equal(series.phase_percent, [0.0, 50.0, 75.0])
    for k, s in enumerate(shift.values()):
        np.testing.assert_allclose(series.points_mm[k] - mesh.points_mm,
                                   np.tile([s, 0.0, 0.0], (mesh.n_points, 1)), atol=1e-9)
