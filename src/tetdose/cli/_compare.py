"""``tetdose compare`` (mesh vs voxel dose report) and ``tetdose export-dose`` (RT Dose).

Both subcommands live here; ``add_args`` tells them apart by the subparser's name.
``compare`` puts the mesh dose on the voxel dose's grid (energy-conserving, mass-weighted with
the mesh's point_data ``density`` when present), then computes gamma maps, DVHs per structure,
profiles through the dose maximum and difference maps, and writes an HTML + JSON report. The
mesh dose exists only inside the mesh (an organ mesh in a hybrid run covers a few organs), so
gamma is evaluated where both doses are defined — voxels at least half inside the mesh — with
the reference maximum taken there too; the report states that region (voxels, cm³).
``export-dose`` writes a mesh dose (resampled the same way) or a dose image onto a CT's grid as a
DICOM RT Dose sharing the CT's Frame of Reference when the CT is a DICOM folder.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from tetdose.errors import ImageError, MeshError, TetdoseError

MESH_SUFFIXES = (".vtu", ".vtk", ".xdmf", ".msh")
#: Gamma criteria of the report: (dose %, DTA mm, local).
CRITERIA = ((3.0, 3.0, False), (2.0, 2.0, False), (3.0, 3.0, True))


def add_args(parser: argparse.ArgumentParser) -> None:
    command = parser.prog.split()[-1]
    parser.set_defaults(_compare_command=command)
    if command == "export-dose":
        parser.add_argument("--dose", required=True, type=Path,
                            help="dose.vtu (cell_data dose, Gy) or a dose image (.nrrd, .mha …)")
        parser.add_argument("--like", required=True, type=Path,
                            help="the CT (DICOM folder, or image) whose grid the RT Dose uses")
        parser.add_argument("-o", "--output", required=True, type=Path, help="rtdose.dcm")
        parser.add_argument("--bits", type=int, choices=(16, 32), default=16)
        return
    parser.add_argument("--mesh-dose", required=True, type=Path,
                        help="dose VTU (cell_data dose) or a folder holding accumulated.vtu")
    parser.add_argument("--voxel-dose", required=True, type=Path,
                        help="dose image (.nrrd …) or a folder holding accumulated.nrrd")
    parser.add_argument("--structures", type=Path,
                        help="label image (0 = background) or a DICOM RTSTRUCT file")
    parser.add_argument("--reference", choices=("voxel", "mesh"), default="voxel",
                        help="which dose is the gamma reference (default voxel)")
    parser.add_argument("--threshold", type=float, default=10.0,
                        help="gamma low-dose threshold [%% of the reference maximum]")
    parser.add_argument("--gamma-max-points", type=int, default=200_000,
                        help="evaluate gamma on a seeded random sample of at most this many "
                             "points above the threshold (pass rate ± its standard error)")
    parser.add_argument("-o", "--output", required=True, type=Path, help="report folder")


def run(args: argparse.Namespace) -> int:
    return _run_export(args) if args._compare_command == "export-dose" else _run_compare(args)


def _find(path: Path, stem: str, suffixes: tuple[str, ...], what: str) -> Path:
    if not path.is_dir():
        return path
    for s in suffixes:
        if (path / f"{stem}{s}").exists():
            return path / f"{stem}{s}"
    found = [p for p in sorted(path.iterdir()) if p.name.endswith(suffixes)
             and "_std" not in p.name]
    if len(found) != 1:
        raise TetdoseError(f"{path} holds {len(found)} {what} files and no {stem}.*; "
                           "name the file itself")
    return found[0]


def _read_mesh_dose(path: Path):  # noqa: ANN202 - (TetMesh, dose)
    from tetdose.io import read_mesh

    mesh = read_mesh(path)
    if "dose" not in mesh.cell_data:
        raise MeshError(f"{path} has no cell_data 'dose'; give a dose VTU from `tetdose dose`")
    return mesh, np.asarray(mesh.cell_data["dose"], dtype=np.float64).reshape(-1)


def _run_compare(args: argparse.Namespace) -> int:
    from tetdose.compare.report import write_report
    from tetdose.io import read_image
    from tetdose.mapping.overlap import compute_overlap
    from tetdose.transfer import mesh_dose_to_grid

    mesh, dose = _read_mesh_dose(_find(args.mesh_dose, "accumulated", MESH_SUFFIXES, "mesh"))
    voxel = read_image(_find(args.voxel_dose, "accumulated", (".nrrd", ".mha", ".nii.gz"),
                             "dose image"))
    voxel = voxel.with_array(np.asarray(voxel.array, dtype=np.float64))
    overlap = compute_overlap(mesh, voxel.grid)
    mesh_img = mesh_dose_to_grid(mesh, dose, voxel.grid, overlap=overlap)
    grid = voxel.grid
    region = (overlap.covered_volume_per_voxel_mm3() >= 0.5 * grid.voxel_volume_mm3
              ).reshape(grid.shape)
    if not region.any():
        raise TetdoseError("no voxel of the dose grid lies at least half inside the mesh; "
                           "compare a mesh dose with a voxel dose of the same patient")
    masks = _structure_masks(args.structures, voxel.grid) if args.structures else {}
    ref, ev = (voxel, mesh_img) if args.reference == "voxel" else (mesh_img, voxel)
    figures, summary = _comparison(mesh, dose, mesh_img, voxel, ref, ev, masks, region, args)
    write_report(args.output, figures, summary)
    reg = summary["region"]
    print(f"compared where both doses exist: {reg['voxels']} voxels ({reg['volume_cm3']:.1f} "
          "cm³) at least half inside the mesh")
    for name, g in summary["gamma"].items():
        print(f"gamma {name}: {g['pass_rate_percent']:.2f} % pass")
    print(f"report → {args.output / 'report.html'}")
    return 0


def _comparison(mesh, dose, mesh_img, voxel, ref, ev, masks, region, args):  # noqa: ANN001, ANN202
    from tetdose.compare import report
    from tetdose.compare.dvh import dvh, image_dvh
    from tetdose.compare.gamma import gamma_index
    from tetdose.compare.profiles import image_profile, mesh_profile

    in_region = np.where(region, ref.array, -np.inf)
    kmax = np.unravel_index(int(np.argmax(in_region)), ref.array.shape)
    norm = float(ref.array[kmax])
    figures = [report.dose_slices_figure(mesh_img, voxel, k=int(kmax[0]))]
    gammas = {}
    for dd, dta, local in CRITERIA:
        g = gamma_index(ref, ev, dose_percent=dd, dta_mm=dta, local=local,
                        threshold_percent=args.threshold, max_points=args.gamma_max_points,
                        mask=region, normalization_gy=norm)
        gammas[g.summary()["criterion"]] = g.summary()
        slice_mask = region.copy()
        slice_mask[:kmax[0]] = False
        slice_mask[kmax[0] + 1:] = False
        g_slice = gamma_index(ref, ev, dose_percent=dd, dta_mm=dta, local=local,
                              threshold_percent=args.threshold, mask=slice_mask,
                              normalization_gy=norm)
        figures.append(report.gamma_figure(g_slice, k=int(kmax[0])))
    covered = mesh_img.array > 0
    structures = {"mesh": (np.ones(mesh.n_tets, bool), covered)}
    tet_voxel = _tet_voxels(mesh, voxel.grid)
    for name, mask in masks.items():
        sel = (tet_voxel >= 0) & mask.ravel()[np.maximum(tet_voxel, 0)]
        structures[name if name != "mesh" else "structure mesh"] = (sel, mask)
    curves, dvh_summary = {}, {}
    for name, (sel, mask) in structures.items():
        if not sel.any() or not mask.any():
            continue
        hm = dvh(dose[sel], mesh.volumes_mm3[sel] / 1000.0, name="mesh")  # by volume [cm³]
        hv = image_dvh(voxel, mask, name="voxel")
        curves[name] = [hm, hv]
        dvh_summary[name] = {"mesh": hm.metrics(), "voxel": hv.metrics()}
    figures.append(report.dvh_figure(curves))
    centre = voxel.grid.index_to_physical(np.array(kmax[::-1], dtype=float))
    lo_mm, hi_mm = mesh.bounds_mm()
    for axis, name in enumerate("xyz"):
        a, b = centre.copy(), centre.copy()
        a[axis], b[axis] = lo_mm[axis], hi_mm[axis]
        figures.append(report.profiles_figure(
            [mesh_profile(mesh, dose, a, b), image_profile(voxel, a, b)], name=f"profile_{name}"))
    above = ref.array >= args.threshold / 100.0 * norm
    diff = (mesh_img.array - voxel.array)[above & region]
    n_region = int(region.sum())
    summary = {"region": {"description": "voxels at least half inside the mesh",
                          "voxels": n_region,
                          "volume_cm3": n_region * voxel.grid.voxel_volume_mm3 / 1000.0,
                          "reference_max_gy": norm},
               "mesh_dose_max_gy": float(dose.max()), "voxel_dose_max_gy": float(voxel.array.max()),
               "mean_abs_difference_gy": float(np.abs(diff).mean()) if diff.size else float("nan"),
               "gamma": gammas, "dvh": dvh_summary}
    return figures, summary


def _labels_on(labels, grid) -> np.ndarray:  # noqa: ANN001
    """Label image sampled at the dose grid's voxel centres (nearest voxel, by position)."""
    if labels.grid.same_as(grid):
        return np.asarray(labels.array).astype(np.int64)
    idx = np.rint(labels.grid.physical_to_index(grid.voxel_centers_mm())).astype(np.int64)
    size = np.array(labels.grid.size)
    ok = np.all((idx >= 0) & (idx < size), axis=1)
    idx[~ok] = 0
    out = np.asarray(labels.array)[idx[:, 2], idx[:, 1], idx[:, 0]].astype(np.int64)
    return np.where(ok, out, 0).reshape(grid.shape)


def _structure_masks(path: Path, grid) -> dict[str, np.ndarray]:  # noqa: ANN001
    """Name → voxel mask on ``grid``: RTSTRUCT ROIs by name, or ``label N`` per image label."""
    from tetdose.compare.rtstruct import is_rtstruct, read_rtstruct, structure_masks
    from tetdose.io import read_image

    if is_rtstruct(path):
        return structure_masks(read_rtstruct(path), grid, skip_unusable=True)
    labels = _labels_on(read_image(path), grid)
    return {f"label {lab}": labels == lab for lab in np.unique(labels[labels > 0])}


def _tet_voxels(mesh, grid) -> np.ndarray:  # noqa: ANN001
    """Flat id of the voxel holding each tet's centroid (−1 off the grid): a tet belongs to a
    structure when that voxel does."""
    idx = np.rint(grid.physical_to_index(mesh.centroids_mm)).astype(np.int64)
    ok = np.all((idx >= 0) & (idx < np.array(grid.size)), axis=1)
    flat = (idx[:, 2] * grid.size[1] + idx[:, 1]) * grid.size[0] + idx[:, 0]
    return np.where(ok, flat, -1)


def _run_export(args: argparse.Namespace) -> int:
    from tetdose.dicom.rt_dose import write_rt_dose
    from tetdose.image import Image
    from tetdose.io import read_image
    from tetdose.transfer import interpolate_at_points, mesh_dose_to_grid

    like = read_image(args.like)
    grid = like.grid
    if args.dose.suffix.lower() in MESH_SUFFIXES:
        mesh, dose = _read_mesh_dose(args.dose)
        img = mesh_dose_to_grid(mesh, dose, grid)
    else:
        src = read_image(args.dose)
        if src.array.ndim != 3:
            raise ImageError(f"{args.dose} is not a 3-D dose image")
        img = src if src.grid.same_as(grid) else Image(
            interpolate_at_points(src, grid.voxel_centers_mm(), outside=0.0).reshape(grid.shape),
            grid)
    img = Image(np.clip(np.asarray(img.array, dtype=np.float64), 0.0, None), grid)
    reference = args.like if args.like.is_dir() else None
    write_rt_dose(img, args.output, reference_ct=reference, bits=args.bits)
    print(f"RT Dose {grid.size}, max {img.array.max():.4g} Gy → {args.output}")
    return 0
