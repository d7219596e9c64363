"""RT Structure Set reading and rasterization: analytic sphere and ring (hole) masks on identity,
flipped and rotated grids, name/number/colour round trip, errors, dciodvfy validity of the
synthetic file, and ``tetdose compare --structures rtstruct.dcm`` end to end.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import warnings
from pathlib import Path

import numpy as np
import pydicom
import pytest
from pydicom.dataset import Dataset
from pydicom.uid import RTStructureSetStorage

from tetdose.core.image import ImageGrid
from tetdose.dicom.modules import ds_values, save, set_equipment, study_context
from tetdose.dicom.rtstruct import (
    Structure,
    even_odd_fill,
    is_rtstruct,
    read_rtstruct,
    structure_mask,
    structure_masks,
)
from tetdose.errors import DicomError, GeometryMismatchError

CENTRE = np.array([1.3, -2.1, 0.7])  # sphere/ring centre [mm], off the voxel lattice
R_MM = 14.0
RING = (5.0, 11.0)  # inner, outer radius [mm]
N_POLY = 256  # polygon vertices per circle (inscribed; sagitta r(1 − cos π/N) < 0.003 mm)
ROT_Z = np.array([[np.cos(0.4), -np.sin(0.4), 0.0], [np.sin(0.4), np.cos(0.4), 0.0], [0, 0, 1.0]])
DIRECTIONS = {"identity": np.eye(3), "y_flipped": np.diag([1.0, -1.0, 1.0]),
              "z_flipped": np.diag([1.0, 1.0, -1.0]), "rotated": ROT_Z}


def make_grid(direction, spacing=(1.5, 1.25, 2.0), size=(28, 32, 20)) -> ImageGrid:
    """A grid centred near CENTRE whose slices are planes of constant patient z."""
    g = ImageGrid((0, 0, 0), spacing, direction, size)
    half = g.index_to_physical((np.array(size) - 1) / 2.0)
    return ImageGrid(CENTRE - half + (0.3, -0.2, 0.0), spacing, direction, size)


def circle(centre, r_mm, z_mm) -> np.ndarray:
    t = np.linspace(0, 2 * np.pi, N_POLY, endpoint=False)
    return np.column_stack([centre[0] + r_mm * np.cos(t), centre[1] + r_mm * np.sin(t),
                            np.full(N_POLY, z_mm)])


def slice_z_mm(grid: ImageGrid) -> np.ndarray:
    return grid.index_to_physical(np.column_stack([np.zeros((grid.size[2], 2)),
                                                   np.arange(grid.size[2])]))[:, 2]


def sphere_and_ring(grid: ImageGrid, z_planes=None) -> list[Structure]:
    """A sphere (circles on every plane) and a ring: outer + inner circles, the inner a hole."""
    zs = slice_z_mm(grid) if z_planes is None else z_planes
    sphere = [circle(CENTRE, np.sqrt(R_MM**2 - (z - CENTRE[2]) ** 2), z) for z in zs
              if abs(z - CENTRE[2]) < R_MM]
    ring = [c for z in zs if abs(z - CENTRE[2]) < 6.0
            for c in (circle(CENTRE, RING[1], z), circle(CENTRE, RING[0], z))]
    return [Structure("Sphere", 3, (255, 0, 0), tuple(sphere)),
            Structure("Ring", 7, (0, 128, 255), tuple(ring))]


def write_rtstruct(path: Path, structures, frame_uid="1.2.826.0.1.3680043.8.498.77",
                   point_roi: bool = False) -> Path:
    """A minimal RT Structure Set (PS3.3 A.19) written with pydicom."""
    ctx = study_context(None, seed="rtstruct-test", frame_of_reference_uid=frame_uid)
    ds = Dataset()
    ctx.apply(ds)
    ds.Modality = "RTSTRUCT"
    ds.SeriesInstanceUID = "1.2.826.0.1.3680043.8.498.78"
    ds.SeriesNumber = 5
    ds.OperatorsName = ""
    set_equipment(ds)
    ds.InstanceNumber = 1
    ds.StructureSetLabel = "tetdose test"
    ds.StructureSetDate = "20240101"
    ds.StructureSetTime = "120000"
    ref_frame = Dataset()
    ref_frame.FrameOfReferenceUID = frame_uid
    ds.ReferencedFrameOfReferenceSequence = [ref_frame]
    ds.StructureSetROISequence, ds.ROIContourSequence, ds.RTROIObservationsSequence = [], [], []
    for s in structures:
        roi = Dataset()
        roi.ROINumber, roi.ReferencedFrameOfReferenceUID = s.number, frame_uid
        roi.ROIName, roi.ROIGenerationAlgorithm = s.name, "MANUAL"
        ds.StructureSetROISequence.append(roi)
        item = Dataset()
        item.ReferencedROINumber = s.number
        item.ROIDisplayColor = list(s.colour)
        item.ContourSequence = []
        for c in s.contours:
            contour = Dataset()
            contour.ContourGeometricType = "CLOSED_PLANAR"
            contour.NumberOfContourPoints = len(c)
            contour.ContourData = ds_values(np.round(c, 4).ravel())
            item.ContourSequence.append(contour)
        if point_roi:
            point = Dataset()
            point.ContourGeometricType = "POINT"
            point.NumberOfContourPoints = 1
            point.ContourData = ["0", "0", "0"]
            item.ContourSequence.append(point)
        ds.ROIContourSequence.append(item)
        obs = Dataset()
        obs.ObservationNumber, obs.ReferencedROINumber = s.number, s.number
        obs.RTROIInterpretedType, obs.ROIInterpreter = "ORGAN", ""
        ds.RTROIObservationsSequence.append(obs)
    save(ds, path, RTStructureSetStorage, "1.2.826.0.1.3680043.8.498.79")
    return path


def analytic(grid: ImageGrid, inside, band_mm: float = 0.02):
    """(expected mask, certain) from the in-plane radius ρ of each voxel centre on contour
    slices; ``certain`` excludes centres within ``band_mm`` of a circle."""
    p = grid.voxel_centers_mm().reshape(*grid.shape, 3)
    rho = np.hypot(p[..., 0] - CENTRE[0], p[..., 1] - CENTRE[1])
    return inside(rho, p[..., 2] - CENTRE[2], band_mm)


def sphere_truth(rho, dz, band):
    r2 = R_MM**2 - dz**2
    r = np.sqrt(np.clip(r2, 0, None))
    return (rho < r) & (r2 > 0), (np.abs(rho - r) > band) | (r2 <= 0)


def ring_truth(rho, dz, band):
    on = np.abs(dz) < 6.0
    exp = on & (rho > RING[0]) & (rho < RING[1])
    return exp, ~on | ((np.abs(rho - RING[0]) > band) & (np.abs(rho - RING[1]) > band))


@pytest.mark.parametrize("name", DIRECTIONS)
def test_masks_match_analytic_sphere_and_ring(tmp_path, name):
    grid = make_grid(DIRECTIONS[name])
    path = write_rtstruct(tmp_path / "rs.dcm", sphere_and_ring(grid))
    masks = structure_masks(read_rtstruct(path), grid)
    assert set(masks) == {"Sphere", "Ring"}
    for key, truth in (("Sphere", sphere_truth), ("Ring", ring_truth)):
        expected, certain = analytic(grid, truth)
        assert masks[key].shape == grid.shape
        assert np.array_equal(masks[key][certain], expected[certain]), key
        assert (~certain).sum() < 0.01 * certain.sum()
    volume = masks["Sphere"].sum() * grid.voxel_volume_mm3
    assert abs(volume / (4 / 3 * np.pi * R_MM**3) - 1) < 0.03
    ring_volume = masks["Ring"].sum() * grid.voxel_volume_mm3
    n_planes = np.sum(np.abs(slice_z_mm(grid) - CENTRE[2]) < 6.0)
    exact = np.pi * (RING[1] ** 2 - RING[0] ** 2) * n_planes * grid.spacing_mm[2]
    assert abs(ring_volume / exact - 1) < 0.03
    k = int(np.argmin(np.abs(slice_z_mm(grid) - CENTRE[2])))
    ij = np.rint(grid.physical_to_index(CENTRE)[:2]).astype(int)
    assert masks["Sphere"][k, ij[1], ij[0]] and not masks["Ring"][k, ij[1], ij[0]]  # the hole


@pytest.mark.parametrize("seed", range(6))
def test_scanline_fill_matches_matplotlib_contains_points(seed):
    """Random star-shaped and self-intersecting polygons, some vertices exactly on scan rows,
    partly off the grid: the scanline parity equals the point-by-point even–odd test."""
    from matplotlib.path import Path as PolygonPath

    rng = np.random.default_rng(seed)
    spacing, size = np.array([0.7, 0.9]), (40, 33)
    n = rng.integers(3, 40)
    if seed % 2:  # self-intersecting: vertices in random order
        poly = rng.uniform(-3.0, 32.0, (n, 2))
    else:  # star-shaped, possibly with a vertex on a row of centres
        t = np.sort(rng.uniform(0, 2 * np.pi, n))
        rad = rng.uniform(4.0, 16.0, n)
        poly = np.column_stack([14 + rad * np.cos(t), 15 + rad * np.sin(t)])
    poly[0, 1] = 9 * spacing[1]  # on a row
    out = np.zeros(size[::-1], bool)
    rows = even_odd_fill(poly, spacing, size)
    out[rows[0]:rows[0] + len(rows[1])] = rows[1]
    jj, ii = np.mgrid[:size[1], :size[0]]
    centres = np.column_stack([ii.ravel() * spacing[0], jj.ravel() * spacing[1]])
    ref = PolygonPath(poly).contains_points(centres).reshape(out.shape)
    def line_distance(a, b):  # distance of every centre to the line through edge (a, b)
        d, c = b - a, centres - a
        return np.abs(d[0] * c[:, 1] - d[1] * c[:, 0]) / np.hypot(*d)

    edge_dist = np.min([line_distance(a, b)
                        for a, b in zip(poly, np.roll(poly, -1, axis=0), strict=True)], axis=0)
    away = edge_dist.reshape(out.shape) > 1e-9  # boundary points are implementation-defined
    assert np.array_equal(out[away], ref[away])
    assert out.any()


def test_round_trip_names_numbers_colours_and_points(tmp_path):
    grid = make_grid(np.eye(3))
    written = sphere_and_ring(grid)
    with pytest.warns(UserWarning, match="POINT"):
        read = read_rtstruct(write_rtstruct(tmp_path / "rs.dcm", written, point_roi=True))
    assert [(s.name, s.number, s.colour) for s in read] == [
        (s.name, s.number, s.colour) for s in written]
    for a, b in zip(read, written, strict=True):
        assert len(a.contours) == len(b.contours)  # the POINT contour was skipped
        for ca, cb in zip(a.contours, b.contours, strict=True):
            np.testing.assert_allclose(ca, cb, atol=1e-4)


def test_coarse_grid_uses_nearest_plane_and_fine_grid_warns(tmp_path):
    fine = make_grid(np.eye(3), spacing=(1.5, 1.25, 1.0), size=(28, 32, 40))
    structures = sphere_and_ring(fine)[:1]
    coarse = ImageGrid(fine.origin_mm, (1.5, 1.25, 3.0), np.eye(3), (28, 32, 13))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        mask = structure_mask(structures[0], coarse)  # 3 planes per slab, no XOR artefact
    expected, certain = analytic(coarse, sphere_truth)
    assert np.array_equal(mask[certain], expected[certain])
    finer = ImageGrid(fine.origin_mm, (1.5, 1.25, 0.5), np.eye(3), (28, 32, 80))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # one empty slice between planes: interpolated
        half = structure_mask(structures[0], finer)
    expected, _ = analytic(finer, sphere_truth)
    assert half[1::2].any()
    assert np.mean(half != expected) < 0.01  # shape-based: the sphere, not every other slice
    sparse = Structure("Sparse", 4, None, structures[0].contours[::4])  # planes 4 mm apart
    with pytest.warns(UserWarning, match="runs of more than 2 slices .* not interpolated"):
        gappy = structure_mask(sparse, finer)
    assert gappy.any(axis=(1, 2)).sum() == len(sparse.contours)  # only the planes' slices


def test_every_other_slice_contours_are_interpolated_shape_based():
    """Issue 27: an RT Structure Set contoured on every other CT slice left every other slice
    empty (MMG then failed); the gaps are filled between the neighbouring planes' shapes."""
    grid = make_grid(np.eye(3), spacing=(1.0, 1.0, 1.0), size=(40, 40, 30))
    zs = slice_z_mm(grid)
    every = sphere_and_ring(grid)[0]
    other = sphere_and_ring(grid, z_planes=zs[::2])[0]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        full, sparse = structure_mask(every, grid), structure_mask(other, grid)
    assert sparse[1::2].sum() > 0.9 * full[1::2].sum()
    assert np.mean(sparse != full) < 0.01 and sparse.sum() == pytest.approx(full.sum(), rel=0.05)


def test_errors_oblique_off_grid_empty_and_not_rtstruct(tmp_path):
    grid = make_grid(np.eye(3))
    tilt = circle(CENTRE, 8.0, 0.0) - CENTRE
    tilt = tilt @ np.array([[1, 0, 0], [0, np.cos(0.5), -np.sin(0.5)], [0, np.sin(0.5),
                                                                      np.cos(0.5)]]).T + CENTRE
    with pytest.raises(GeometryMismatchError, match="oblique"):
        structure_mask(Structure("Tilted", 1, None, (tilt,)), grid)
    far = Structure("Far", 2, None, (circle(CENTRE, 5.0, CENTRE[2] + 500.0),))
    with pytest.raises(GeometryMismatchError, match="off the grid"):
        structure_mask(far, grid)
    empty = Structure("Empty", 3, None, ())
    with pytest.raises(DicomError, match="no closed planar contours"):
        structure_masks([empty], grid)
    with pytest.warns(UserWarning, match="left out"):
        assert structure_masks([empty, far], grid, skip_unusable=True) == {}
    ct = tmp_path / "ct.dcm"
    ds = Dataset()
    ds.Modality = "CT"
    save(ds, ct, pydicom.uid.CTImageStorage, "1.2.3.4")
    text = tmp_path / "labels.txt"
    text.write_text("not dicom")
    assert not is_rtstruct(ct) and not is_rtstruct(text) and not is_rtstruct(tmp_path)
    with pytest.raises(DicomError, match="not RTSTRUCT"):
        read_rtstruct(ct)
    with pytest.raises(DicomError, match="cannot read"):
        read_rtstruct(text)


def test_synthetic_rtstruct_passes_dciodvfy(tmp_path):
    if shutil.which("dciodvfy") is None:
        pytest.skip("dciodvfy (Debian package dicom3tools) is not installed")
    path = write_rtstruct(tmp_path / "rs.dcm", sphere_and_ring(make_grid(np.eye(3))))
    assert is_rtstruct(path)
    run = subprocess.run(["dciodvfy", str(path)], capture_output=True, text=True, check=False)
    assert [line for line in (run.stdout + run.stderr).splitlines() if "Error" in line] == []


def test_cli_compare_with_rtstruct(tmp_path, capsys):
    from tetdose.cli import main
    from tetdose.core.io import write_image, write_mesh
    from tetdose.core.transfer import mesh_dose_to_grid

    from helpers import box_mesh

    grid = make_grid(np.eye(3), spacing=(2.0, 2.0, 2.0), size=(20, 20, 16))
    lo, hi = grid.index_to_physical([0, 0, 0]), grid.index_to_physical(np.array(grid.size) - 1)
    mesh = box_mesh(lo, hi, (6, 6, 5))
    dose = 1.0 + 0.05 * (mesh.centroids_mm[:, 0] - CENTRE[0])  # rising along x
    write_mesh(tmp_path / "dose.vtu", mesh.with_data(cell_data={"dose": dose}))
    write_image(tmp_path / "vdose.nrrd", mesh_dose_to_grid(mesh, dose, grid))
    sphere = sphere_and_ring(grid)[0]
    right = Structure("Right", 9, (0, 255, 0),
                      tuple(c + (8.0, 0.0, 0.0) for c in sphere_and_ring(grid)[1].contours))
    write_rtstruct(tmp_path / "rs.dcm", [sphere, right])
    out = tmp_path / "report"
    assert main(["compare", "--mesh-dose", str(tmp_path / "dose.vtu"), "--voxel-dose",
                 str(tmp_path / "vdose.nrrd"), "--structures", str(tmp_path / "rs.dcm"), "-q",
                 "--gamma-max-points", "2000",
                 "-o", str(out)]) == 0
    dvhs = json.loads((out / "summary.json").read_text())["dvh"]
    assert set(dvhs) == {"mesh", "Sphere", "Right"}
    mask = structure_masks([sphere], grid)["Sphere"]
    voxel_dose = mesh_dose_to_grid(mesh, dose, grid).array
    assert dvhs["Sphere"]["voxel"]["Dmean"] == pytest.approx(voxel_dose[mask].mean(), rel=1e-9)
    assert dvhs["Right"]["voxel"]["Dmean"] > dvhs["Sphere"]["voxel"]["Dmean"] + 0.2
    assert dvhs["Sphere"]["mesh"]["Dmean"] == pytest.approx(dvhs["Sphere"]["voxel"]["Dmean"],
                                                           abs=0.1)
    assert "pass" in capsys.readouterr().out
