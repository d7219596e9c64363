"""``tetdose evaluate``: the paper's metrics (eq. 21–26), error images and slice figures.

Two modes: one mapped mesh against the CT it was mapped from (``--ct --mesh``), or, per phase,
the deformed phase meshes of ``deform`` against the real phase CTs of a 4D-CT (``--phases
--4dct``): each phase's mesh density voxelized on that phase CT's grid (the virtual CT) is
compared with the real phase CT inside the mesh — the check that the mesh motion and the
mass-conserving density reproduce the real anatomy. Phases are matched by percentage.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from tetdose._atomic import atomic_write_file
from tetdose.cli._common import add_calibration_arg, calibration_from, read_mapped_mesh
from tetdose.core.io import read_image, read_labels, write_image
from tetdose.errors import ImageError, TetdoseError
from tetdose.mapping.figures import plot_evaluation
from tetdose.mapping.metrics import evaluate


def add_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--ct", help="the CT the mesh was mapped from (HU)")
    p.add_argument("--mesh", help="mapped mesh (point_data 'density' in g/cm³)")
    p.add_argument("--phases", help="per-phase mode: folder written by `tetdose deform`")
    p.add_argument("--4dct", dest="ct4d", nargs="+",
                   help="per-phase mode: the real 4D-CT (a folder, or one image file per phase)")
    p.add_argument("--mask", help="label image defining the ROI (default: voxels ≥ 50 %% in mesh)")
    p.add_argument("--label", type=int, action="append",
                   help="label value(s) of --mask forming the ROI (default: any non-zero)")
    p.add_argument("-o", "--output", required=True, help="output folder")
    add_calibration_arg(p)


def run(args: argparse.Namespace) -> int:
    if args.phases or args.ct4d:
        if not (args.phases and args.ct4d) or args.ct or args.mesh:
            raise TetdoseError("per-phase evaluation takes --phases and --4dct (not --ct/--mesh)")
        return _run_phases(args)
    if not (args.ct and args.mesh):
        raise TetdoseError("give --ct and --mesh (one mapping), or --phases and --4dct (per phase)")
    mesh = read_mapped_mesh(args.mesh)
    ct = read_image(args.ct)
    roi = None
    if args.mask:
        roi = _roi_from_mask(read_labels(args.mask, f"--mask {args.mask}"), ct, args.label)
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


def _run_phases(args: argparse.Namespace) -> int:
    from tetdose.motion import PhaseSeries
    from tetdose.motion.ct4d_read import SERIES_FIX, find_phase, read_4dct

    series = PhaseSeries.read(None, args.phases)
    if series.density_g_cm3 is None:
        raise TetdoseError(f"{args.phases} carries no phase densities; write it with `tetdose deform`")
    ct_phases = read_4dct(args.ct4d[0] if len(args.ct4d) == 1 else args.ct4d)
    calibration = calibration_from(args)
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for k, pct in enumerate(series.phase_percent):
        real = ct_phases[find_phase(ct_phases, float(pct), fix=SERIES_FIX,
                                    what=f" for the phase mesh at {pct:g} %")]
        roi = None if not args.mask else _roi_from_mask(read_labels(args.mask), real.image,
                                                        args.label)
        ev = evaluate(real.image, series.mesh(k), series.density_g_cm3[k],
                      calibration=calibration, roi=roi)
        plot_evaluation(ev, out / f"phase_{pct:05.1f}.png", title=f"phase {pct:g} %")
        rows.append({"phase_percent": float(pct), "ct_source": real.source,
                     **ev.metrics.as_dict()})
        m = ev.metrics
        print(f"phase {pct:g} %: {m.n_voxels} voxels, RMDE {m.rmde_pct:.3f} %, ESD "
              f"{m.esd_pct:.3f} %, mass error {m.mass_error_pct:.3f} % (eq. 23), "
              f"{m.mass_error_in_mesh_pct:.3f} % in mesh")
    keys = [k for k in rows[0] if k != "ct_source"]
    with atomic_write_file(out / "phases.csv") as tmp:
        tmp.write_text("\n".join([",".join(keys)] + [",".join(repr(r[k]) for k in keys)
                                                      for r in rows]) + "\n")
    with atomic_write_file(out / "metrics.json") as tmp:
        tmp.write_text(json.dumps({"phases": rows}, indent=2))
    print(f"{len(rows)} phases: virtual vs real CT → {out}")
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
