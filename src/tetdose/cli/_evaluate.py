"""``tetdose evaluate``: the paper's metrics (eq. 21–26), error images and slice figures."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from tetdose._atomic import atomic_write_file
from tetdose.cli._common import add_calibration_arg, calibration_from, read_mapped_mesh
from tetdose.errors import ImageError
from tetdose.io import read_image, write_image
from tetdose.mapping.figures import plot_evaluation
from tetdose.mapping.metrics import evaluate


def add_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--ct", required=True, help="the CT the mesh was mapped from (HU)")
    p.add_argument("--mesh", required=True, help="mapped mesh (point_data 'density' in g/cm³)")
    p.add_argument("--mask", help="label image defining the ROI (default: voxels ≥ 50 %% in mesh)")
    p.add_argument("--label", type=int, action="append",
                   help="label value(s) of --mask forming the ROI (default: any non-zero)")
    p.add_argument("-o", "--output", required=True, help="output folder")
    add_calibration_arg(p)


def run(args: argparse.Namespace) -> int:
    mesh = read_mapped_mesh(args.mesh)
    ct = read_image(args.ct)
    roi = None
    if args.mask:
        roi = _roi_from_mask(read_image(args.mask), ct, args.label)
    ev = evaluate(ct, mesh, np.asarray(mesh.point_data["density"]),
                  calibration=calibration_from(args), roi=roi)
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    write_image(out / "reconstruction.nrrd", ev.reconstruction.with_array(
        ev.reconstruction.array.astype(np.float32)))
    write_image(out / "error.nrrd", ev.abs_error.with_array(ev.abs_error.array.astype(np.float32)))
    write_image(out / "relative_error.nrrd", ev.relative_error_pct.with_array(
        ev.relative_error_pct.array.astype(np.float32)))
    plot_evaluation(ev, out / "slices.png", title=Path(args.mesh).name)
    with atomic_write_file(out / "metrics.json") as tmp:
        tmp.write_text(json.dumps(ev.metrics.as_dict(), indent=2))
    m = ev.metrics
    print(f"{m.n_voxels} voxels: RMDE {m.rmde_pct:.3f} %, ESD {m.esd_pct:.3f} %, mass error "
          f"{m.mass_error_pct:.3f} % (eq. 23), {m.mass_error_in_mesh_pct:.2e} % in mesh → {out}")
    return 0


def _roi_from_mask(mask, ct, labels):  # noqa: ANN001, ANN202
    """ROI on the CT grid from a label image, resampled by physical coordinates (nearest)."""
    import SimpleITK as sitk

    if not mask.grid.same_as(ct.grid):
        resampled = sitk.Resample(mask.to_sitk(), ct.to_sitk(), sitk.Transform(),
                                  sitk.sitkNearestNeighbor, 0)
        arr = sitk.GetArrayFromImage(resampled)
    else:
        arr = mask.array
    roi = np.isin(arr, labels) if labels else arr != 0
    if not roi.any():
        raise ImageError("the mask holds no voxel of the requested label(s) on the CT grid")
    return roi
