"""Small bad (and good) inputs for the command-line error table (tests/unit/test_cli_errors.py).

:func:`build` writes every file once into one folder; each name says what is wrong with it.
"""

from __future__ import annotations

import textwrap
from pathlib import Path

import meshio
import numpy as np
import pydicom
import SimpleITK as sitk

from tetdose.core.calibration import HUCalibration
from tetdose.core.image import Image
from tetdose.core.io import write_image, write_mesh
from tetdose.dicom.ct_series import write_ct_series
from tetdose.motion import PhaseSeries

from helpers import box_mesh, density_image, grid_for

CAL = HUCalibration.schneider2000()

#: A point source on the CT's axis, aimed at the mesh (mm, patient frame).
PLAN = """
[[beam]]
type = "point"
energy_mev = 1.0
position_mm = [12.0, 10.0, -100.0]
direction = [0.0, 0.0, 1.0]
half_angle_deg = 3.0
"""


def _raw_mesh(path: Path, points: np.ndarray, cells: list, **point_data: np.ndarray) -> None:
    meshio.write(path, meshio.Mesh(points, cells, point_data=point_data))


def _dicom_variant(src: list[Path], out: Path, edit) -> None:  # noqa: ANN001
    """Copy a DICOM series into ``out`` with ``edit(dataset, k)`` applied to slice k
    (``edit`` returning False drops the slice)."""
    out.mkdir()
    for k, f in enumerate(src):
        ds = pydicom.dcmread(f)
        if edit(ds, k) is not False:
            ds.save_as(out / f.name)


def _shear(ds, k) -> None:  # noqa: ANN001 - a gantry tilt: slices shift along y
    pos = [float(v) for v in ds.ImagePositionPatient]
    ds.ImagePositionPatient = [pos[0], pos[1] + 0.35 * k, pos[2]]


def _plan(d: Path, name: str, text: str) -> None:
    (d / name).write_text(textwrap.dedent(text))


def _images(d: Path) -> Image:
    grid = grid_for([0, 0, 0], [24, 20, 16], [2.0, 2.0, 2.0])
    rho = density_image(grid, lambda x, y, z: np.where(x < 12, 0.26, 1.05) + 0.002 * y)
    ct = rho.with_array(np.round(CAL.hu_of(rho.array)).astype(np.int16))
    write_image(d / "ct.nrrd", ct)
    write_image(d / "ct_u16.nrrd", ct.with_array(ct.array.astype(np.uint16)))  # wrapped HU
    write_image(d / "ct_i8.nrrd", ct.with_array(np.clip(ct.array, -128, 127).astype(np.int8)))
    nan_ct = ct.array.astype(np.float32)
    nan_ct[3, 4, 5] = np.nan
    write_image(d / "ct_nan.nrrd", ct.with_array(nan_ct))
    sitk.WriteImage(sitk.GetImageFromArray(np.zeros((5, 6), np.int16)), str(d / "ct_2d.nrrd"))
    frame = sitk.GetImageFromArray(np.zeros((3, 4, 5), np.int16))
    sitk.WriteImage(sitk.JoinSeries([frame, frame]), str(d / "ct_4d.nrrd"))
    (d / "empty.nrrd").write_bytes(b"")
    (d / "garbage.nrrd").write_bytes(np.random.default_rng(0).bytes(300))
    write_image(d / "zero_dose.nrrd", ct.with_array(np.zeros(ct.array.shape, np.float32)))
    write_image(d / "dose.nrrd", ct.with_array(np.ones(ct.array.shape, np.float32)))
    write_image(d / "labels.nrrd", ct.with_array((ct.array > -500).astype(np.uint8)))
    coarse = grid_for([0, 0, 0], [24, 20, 16], [4.0, 4.0, 4.0])
    write_image(d / "ct_coarse.nrrd", Image(np.zeros(coarse.shape, np.int16) - 1000, coarse))

    series = write_ct_series(Image(ct.array, ct.grid), d / "dicom_ok")
    _dicom_variant(series, d / "dicom_missing", lambda ds, k: k != 3)
    _dicom_variant(series, d / "dicom_mr", lambda ds, k: setattr(ds, "Modality", "MR"))
    _dicom_variant(series, d / "dicom_slope0", lambda ds, k: setattr(ds, "RescaleSlope", "0"))
    _dicom_variant(series, d / "dicom_sheared", _shear)
    _dicom_variant(series, d / "dicom_skewed", lambda ds, k: setattr(
        ds, "ImageOrientationPatient", [1, 0, 0, 0.2, 0.98, 0]))
    return ct


def _meshes(d: Path) -> None:
    mesh = box_mesh([3, 3, 2], [21, 17, 14], (3, 3, 2), jitter=0.2)
    write_mesh(d / "mesh.vtu", mesh)
    vtu = (d / "mesh.vtu").read_bytes()
    (d / "empty.vtu").write_bytes(b"")
    (d / "truncated.vtu").write_bytes(vtu[: len(vtu) // 2])
    (d / "garbage.vtu").write_bytes(np.random.default_rng(1).bytes(500))
    pts, tets = mesh.points_mm, mesh.tets
    _raw_mesh(d / "triangles.vtu", pts, [("triangle", tets[:, :3])])
    nan_pts = pts.copy()
    nan_pts[5] = np.nan
    _raw_mesh(d / "nan_points.vtu", nan_pts, [("tetra", tets)])
    inverted = tets.copy()
    inverted[0, [0, 1]] = inverted[0, [1, 0]]
    _raw_mesh(d / "inverted.vtu", pts, [("tetra", inverted)])
    flat = np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0], [5, 5, 0], [0, 0, 10.0]]) + 4
    _raw_mesh(d / "flat.vtu", flat, [("tetra", np.array([[0, 1, 2, 4], [0, 1, 2, 3]]))])
    far_pts = pts.copy()
    far_pts[np.argmax(pts[:, 0])] = [1e12, 0, 0]
    _raw_mesh(d / "far_point.vtu", far_pts, [("tetra", tets)])
    write_mesh(d / "outside.vtu", box_mesh([500, 500, 500], [510, 510, 510], (1, 1, 1)))
    ones = np.ones(mesh.n_points)
    write_mesh(d / "mapped.vtu", mesh.with_data(point_data={"density": ones}))
    nan_rho = ones.copy()
    nan_rho[7] = np.nan
    write_mesh(d / "nan_density.vtu", mesh.with_data(point_data={"density": nan_rho}))
    write_mesh(d / "neg_density.vtu", mesh.with_data(point_data={"density": ones - 2.0}))
    _raw_mesh(d / "inverted_mapped.vtu", pts, [("tetra", inverted)], density=ones)
    # the tets of the upper half get their own copies of the points they use: same points, two
    # ids, so the mesh falls apart along the middle (transport would lose the energy there)
    upper = mesh.centroids_mm[:, 2] > 8.0
    copy_of = np.unique(tets[upper])
    new_id = np.arange(mesh.n_points)
    new_id[copy_of] = mesh.n_points + np.arange(len(copy_of))
    dup_tets = np.where(upper[:, None], new_id[tets], tets)
    dup_pts = np.concatenate([pts, pts[copy_of]])
    _raw_mesh(d / "duplicates.vtu", dup_pts, [("tetra", dup_tets)],
              density=np.ones(len(dup_pts)))
    dose = mesh.with_data(point_data={"density": ones}, cell_data={"dose": np.zeros(mesh.n_tets)})
    write_mesh(d / "zero_dose.vtu", dose)
    write_mesh(d / "dose.vtu", dose.with_data(cell_data={"dose": np.ones(mesh.n_tets)}))
    series = PhaseSeries(mesh.with_data(point_data={"density": ones}),
                         np.stack([pts, pts + [0, 0, 0.5]]), density_g_cm3=np.stack([ones, ones]))
    series.write(d / "phases")
    other = box_mesh([3, 3, 2], [21, 17, 14], (2, 2, 2))
    (d / "phases_mixed").mkdir()
    for f in ("phases.pvd", "phase_000.vtu"):
        (d / "phases_mixed" / f).write_bytes((d / "phases" / f).read_bytes())
    write_mesh(d / "phases_mixed" / "phase_001.vtu",
               other.with_data(point_data={"density": np.ones(other.n_points)}))
    write_mesh(d / "phase_other.vtu", other.with_data(point_data={"density":
                                                                  np.ones(other.n_points)}))


def _plans(d: Path) -> None:
    _plan(d, "plan.toml", PLAN)
    _plan(d, "plan_unknown_key.toml", PLAN + 'colour = "red"\n')
    _plan(d, "plan_position_word.toml", PLAN.replace("[12.0, 10.0, -100.0]", '"here"'))
    _plan(d, "plan_energy_high.toml", PLAN.replace("energy_mev = 1.0", "energy_mev = 500.0"))
    _plan(d, "plan_energy_negative.toml", PLAN.replace("energy_mev = 1.0", "energy_mev = -1.0"))
    _plan(d, "plan_miss.toml", PLAN.replace("direction = [0.0, 0.0, 1.0]",
                                            "direction = [0.0, 0.0, -1.0]"))
    (d / "bad_cal.csv").write_text("HU,density\n0,1.0\n-100,0.9\n")


def build(d: Path) -> Path:
    """Write every input into ``d`` (returned)."""
    _images(d)
    _meshes(d)
    _plans(d)
    return d
