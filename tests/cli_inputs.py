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
from tetdose.core.io import read_mesh, write_image, write_mesh
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


def _edit_dicom(src: Path, out: Path, **values: str) -> Path:
    """A copy of the DICOM file ``src`` with attributes set (PatientID="B", …)."""
    ds = pydicom.dcmread(src)
    for keyword, value in values.items():
        setattr(ds, keyword, value)
    ds.save_as(out)
    return out


def _rtstruct(path: Path, reference: Path, names: list[str], frame_uid: str | None = None
              ) -> Path:
    """A minimal RT Structure Set of the CT series ``reference`` (its patient and frame unless
    ``frame_uid``): one square ROI per name, numbered 1, 2 …, contoured on every slice."""
    from pydicom.dataset import Dataset
    from pydicom.uid import RTStructureSetStorage

    from tetdose.dicom.modules import save, set_equipment, study_context

    ctx = study_context(reference, seed="cli-rtstruct", frame_of_reference_uid=frame_uid)
    ds = Dataset()
    ctx.apply(ds)
    ds.Modality, ds.SeriesInstanceUID, ds.SeriesNumber = "RTSTRUCT", "1.2.826.0.1.3680043.8.498.7", 5
    set_equipment(ds)
    ds.StructureSetLabel = "cli"
    ref = Dataset()
    ref.FrameOfReferenceUID = ctx.frame_of_reference_uid
    ds.ReferencedFrameOfReferenceSequence = [ref]
    ds.StructureSetROISequence, ds.ROIContourSequence = [], []
    for number, name in enumerate(names, start=1):
        roi = Dataset()
        roi.ROINumber, roi.ROIName = number, name
        roi.ReferencedFrameOfReferenceUID = ctx.frame_of_reference_uid
        ds.StructureSetROISequence.append(roi)
        item = Dataset()
        item.ReferencedROINumber, item.ContourSequence = number, []
        lo = 3.0 + 6.0 * (number - 1)
        for z in np.arange(2.0, 13.0, 2.0):
            c = Dataset()
            c.ContourGeometricType, c.NumberOfContourPoints = "CLOSED_PLANAR", 4
            c.ContourData = [f"{v:g}" for v in (lo, 3, z, lo + 9, 3, z, lo + 9, 15, z, lo, 15, z)]
            item.ContourSequence.append(c)
        ds.ROIContourSequence.append(item)
    save(ds, path, RTStructureSetStorage, f"1.2.826.0.1.3680043.8.498.8.{len(names)}")
    return path


def _boundaries(d: Path, ct: Image) -> None:
    """Inputs of issue 23: other patients and frames, units, label images, tiny labels."""
    from tetdose.dicom.ct_series import write_ct_series_4d
    from tetdose.plan.beams import ControlPoint, LinacBeam
    from tetdose.plan.rt_plan import write_rt_plan
    from tetdose.transport import Plan

    ok = d / "dicom_ok"
    plan = Plan(treatment_beams=(LinacBeam("AP", "6MV", (11.0, 9.0, 7.0),
                                           (ControlPoint(0, 0, 0, (-20, 20, -20, 20)),)),))
    write_rt_plan(plan, d / "rtplan.dcm", reference_ct=ok)
    _edit_dicom(d / "rtplan.dcm", d / "rtplan_other_patient.dcm", PatientID="SOMEONE-ELSE")
    _edit_dicom(d / "rtplan.dcm", d / "rtplan_other_frame.dcm",
                FrameOfReferenceUID="1.2.826.0.1.3680043.8.498.999")
    _plan(d, "plan_linac.toml", '[materials]\n0 = "water"\n')
    _rtstruct(d / "rs.dcm", ok, ["GTV", "Lung"])
    _rtstruct(d / "rs_other_frame.dcm", ok, ["GTV"], frame_uid="1.2.826.0.1.3680043.8.498.998")
    _rtstruct(d / "rs_two_gtv.dcm", ok, ["GTV", "GTV"])
    # a 4D-CT whose second phase belongs to another patient (and study)
    phases = write_ct_series_4d([ct, ct], d / "ct4d_mixed", phase_percent=[0, 50])
    for f in sorted(phases[1].iterdir()):
        _edit_dicom(f, f, PatientID="SOMEONE-ELSE")
    phases = write_ct_series_4d([ct, ct], d / "ct4d_two_studies", phase_percent=[0, 50])
    for f in sorted(phases[1].iterdir()):
        _edit_dicom(f, f, StudyInstanceUID="1.2.826.0.1.3680043.8.498.997")
    # the mapped mesh written in metres, in a tenth of a mm (too large), and in cm
    mapped = read_mesh(d / "mapped.vtu")
    write_mesh(d / "mapped_in_m.vtu", mapped.moved(mapped.points_mm / 1000.0))
    write_mesh(d / "mapped_x20.vtu", mapped.moved(mapped.points_mm * 20.0))
    # a segmentation resampled linearly: fractions at the label borders
    lab = (ct.array > -500).astype(np.float32)
    lab[:, :, 5:7] = 0.5
    write_image(d / "labels_linear.nrrd", ct.with_array(lab))
    one = (ct.array > -500).astype(np.uint8)
    one[4, 5, 2] = 2  # a one-voxel label, inside the background (x = 4 mm)
    write_image(d / "labels_one_voxel.nrrd", ct.with_array(one))
    # a prescription by D95 on the labelled half of the CT, for very few histories
    _plan(d, "plan_rx.toml", PLAN.replace("half_angle_deg = 3.0", "half_angle_deg = 8.0")
          + '[materials]\n0 = "lung"\n1 = "water"\n[regions]\ntissue = 1\n'
          '[prescription]\nstructure = "tissue"\ndose_gy = 2.0\nmetric = "D95"\n')
    (d / "not_dicom").mkdir()
    (d / "not_dicom" / "notes.txt").write_text("not an image")


def build(d: Path) -> Path:
    """Write every input into ``d`` (returned)."""
    ct = _images(d)
    _meshes(d)
    _plans(d)
    _boundaries(d, ct)
    return d
