"""``tetdose mesh --labels L [--label N …] [--size-mm 2=8,3=3] [--body auto|N] -o mesh.vtu``:
one conforming tetrahedral mesh of the labels (MMG), with checks printed and written as JSON.

MMG runs in a child process (:mod:`tetdose.meshing.worker`): progress is printed per stage and
per cut of labels, with an estimate first; a job whose estimate exceeds the available memory or
``--max-minutes`` is refused before MMG runs unless ``--force``; Ctrl-C / SIGTERM stop it at
once (exit 130 / 143, nothing written)."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

from tetdose.errors import TetdoseError

#: Default time limit of a meshing job [min] (the estimate of :func:`tetdose.meshing.mmg.estimate`).
DEFAULT_MAX_MINUTES = 120.0


def add_args(parser: argparse.ArgumentParser) -> None:
    src = parser.add_argument_group("input (a label image, or an RT Structure Set with --ct)")
    src.add_argument("--labels", metavar="IMAGE",
                     help="integer label image (NRRD / MHA / NIfTI / DICOM SEG)")
    src.add_argument("--structures", metavar="RTSTRUCT",
                     help="RT Structure Set; its ROIs (--roi) are rasterized on the --ct grid")
    src.add_argument("--roi", action="append", metavar="NAME",
                     help="ROI of --structures to mesh (repeat; ROI i becomes label i)")
    src.add_argument("--ct", metavar="CT", help="CT (file or DICOM folder): the grid for "
                     "--structures and the image for --body auto")
    parser.add_argument("--label", type=int, action="append", metavar="N",
                        help="label to mesh (repeat for several; default: every non-zero label)")
    parser.add_argument("--size-mm", default=None, metavar="H|L=H,…",
                        help="target edge in mm: one value for all labels, or per label "
                             "'2=8,3=3' (labels not named: default from their size)")
    parser.add_argument("--body", default=None, metavar="auto|N",
                        help="'auto': add the patient outline from --ct (threshold −500 HU, "
                             "largest component, holes filled) around the labels; N: the body "
                             "is label N of the image")
    parser.add_argument("--mesher", choices=("mmg", "gmsh"), default="mmg",
                        help="mmg (default): one conforming multi-label mesh; gmsh: each label "
                             "separately (interfaces do not conform)")
    parser.add_argument("--smooth", type=float, default=None, metavar="SIGMA",
                        help="Gaussian blur in voxels (mmg: of the distance fields, default "
                             "0.75; gmsh: of each mask before marching cubes, default 0)")
    parser.add_argument("--max-minutes", type=float, default=DEFAULT_MAX_MINUTES, metavar="MIN",
                        help="refuse a job estimated to take longer (default "
                             f"{DEFAULT_MAX_MINUTES:g}); the memory limit is what is available")
    parser.add_argument("--force", action="store_true",
                        help="run even if the estimate exceeds the time or memory limit")
    parser.add_argument("-o", "--output", required=True, metavar="MESH",
                        help="output mesh (VTU recommended), cell_data region = label; the "
                             "checks go to MESH's name + .checks.json")


def parse_sizes(text: str | None) -> float | dict[int, float] | None:
    """'6' → 6.0; '2=8,3=3' → {2: 8.0, 3: 3.0}; None → None (defaults)."""
    if text is None:
        return None
    try:
        sizes = float(text) if "=" not in text else \
            {int(k): float(v) for k, v in (item.split("=") for item in text.split(","))}
    except ValueError as exc:
        raise TetdoseError(f"cannot read --size-mm {text!r}; write 6 or 2=8,3=3") from exc
    values = list(sizes.values()) if isinstance(sizes, dict) else [sizes]
    if not all(math.isfinite(v) and v > 0 for v in values):
        raise TetdoseError(f"--size-mm {text!r}: target edges must be finite and > 0 mm")
    return sizes


def _inputs(args: argparse.Namespace):  # noqa: ANN202 - (Image, list[int] | None, names)
    import numpy as np

    from tetdose.core.io import read_image
    from tetdose.meshing.inputs import labels_from_structures, with_body

    if (args.labels is None) == (args.structures is None):
        raise TetdoseError("give either --labels IMAGE or --structures RTSTRUCT (with --ct)")
    ct = read_image(args.ct) if args.ct else None
    names: dict[int, str] = {}
    if args.structures:
        if ct is None:
            raise TetdoseError("--structures needs --ct CT: the ROIs are rasterized on its grid")
        labels, names = labels_from_structures(args.structures, ct, args.roi or [])
    else:
        labels = read_image(args.labels)
    ids = args.label
    if args.body is not None:
        if args.body == "auto":
            if ct is None:
                raise TetdoseError("--body auto needs --ct CT to find the patient outline")
            labels, body = with_body(labels, ct)
            names[body] = "body"
        else:
            try:
                body = int(args.body)
            except ValueError as exc:
                raise TetdoseError(f"--body takes 'auto' or a label number, got {args.body!r}"
                                   ) from exc
            present = sorted(int(v) for v in np.unique(labels.array) if v != 0)
            if body not in present:
                raise TetdoseError(f"--body {body}: the label image has no label {body} (its "
                                   f"labels: {present}); name the body's label, or --body auto "
                                   "with --ct")
        if ids is not None and body not in ids:
            ids = [*ids, body]
    return labels, ids, names


def run(args: argparse.Namespace) -> int:
    from tetdose._atomic import atomic_write_file
    from tetdose.cli._common import check_output
    from tetdose.core.io import MESH_SUFFIXES, write_mesh
    from tetdose.meshing import mesh_checks, mesh_label_image

    check_output(args, suffixes=MESH_SUFFIXES)
    sizes = parse_sizes(args.size_mm)
    if not (math.isfinite(args.max_minutes) and args.max_minutes > 0):
        raise TetdoseError(f"--max-minutes must be a number > 0, got {args.max_minutes:g}")
    labels, ids, names = _inputs(args)
    if args.mesher == "mmg":
        from tetdose.meshing.mmg import Budget, available_memory_bytes
        from tetdose.meshing.worker import mesh_in_child

        smooth = 0.75 if args.smooth is None else args.smooth
        budget = None if args.force else Budget(60.0 * args.max_minutes, available_memory_bytes())
        mesh = mesh_in_child(labels, ids, sizes, smoothing_vox=smooth, budget=budget,
                             on_progress=None if args.quiet else _progress)
    else:
        if isinstance(sizes, dict):
            raise TetdoseError("--mesher gmsh takes one --size-mm for all labels")
        mesh = mesh_label_image(labels, ids, 6.0 if sizes is None else sizes,
                                smoothing_sigma_vox=args.smooth or 0.0)
    report = mesh_checks(mesh, labels)  # before writing: a mesh that fails them is not written
    path = write_mesh(args.output, mesh)
    report["mesher"] = args.mesher
    report["names"] = {str(k): v for k, v in names.items()}
    json_path = checks_path(path)
    with atomic_write_file(json_path) as tmp:
        Path(tmp).write_text(json.dumps(report, indent=2) + "\n")
    _print(report, names, path, json_path)
    return 0


def _progress(event: str, info: dict) -> None:
    """One line on stderr per meshing stage and per cut (see tetdose.meshing.mmg.Progress)."""
    import sys

    from tetdose.meshing.mmg import MeshingEstimate, duration_text

    if event == "start":
        est = MeshingEstimate(**info["estimate"])
        line = f"{info['labels']} labels: {est.describe()} (estimate)"
    elif event == "background":
        line = f"background mesh: {info['tets']} tets"
    elif event == "cut":
        labels = ", ".join(str(lab) for lab in info["labels"])
        line = (f"cut label{'s' * (len(info['labels']) > 1)} {labels}: {info['done']}/"
                f"{info['total']} labels in {duration_text(info['elapsed_s'])}, about "
                f"{duration_text(info['left_s'])} of cutting left")
    elif event == "remesh":
        line = f"remeshing {info['tets']} tets to the target sizes, then the sliver pass"
    else:
        return
    print(f"tetdose mesh: {line}", file=sys.stderr, flush=True)


def output_files(args: argparse.Namespace) -> list[Path]:
    """The file ``run`` writes beside ``-o``: the checks JSON."""
    return [checks_path(Path(args.output))]


def checks_path(output: Path) -> Path:
    """``mesh.checks.json`` beside ``mesh.vtu``."""
    return output.with_name(output.name.rsplit(".", 1)[0] + ".checks.json")


def _print(report: dict, names: dict[int, str], path: Path, json_path: Path) -> None:
    c = report["conformity"]
    print(f"{report['n_tets']} tets / {report['n_points']} points, dihedral min "
          f"{report['min_dihedral_deg']:.1f}° median {report['median_dihedral_deg']:.1f}°, "
          f"{report['inverted']} inverted, {c['interface_faces']} interface faces, "
          f"{c['coincident_vertices']} coincident vertices → {path}")
    print(f"{'label':>12} {'tets':>8} {'cm³':>9} {'voxel cm³':>10} {'Δvol %':>7} "
          f"{'min°':>6} {'med°':>6} {'dist mm':>8} {'p95 mm':>7}")
    for lab, e in report["labels"].items():
        name = names.get(int(lab), lab)
        dv = "—" if e["volume_error_pct"] is None else f"{e['volume_error_pct']:+.2f}"
        print(f"{name:>12} {e['tets']:>8} {e['volume_cm3']:>9.3f} {e['voxel_volume_cm3']:>10.3f} "
              f"{dv:>7} {e.get('min_dihedral_deg', float('nan')):>6.1f} "
              f"{e.get('median_dihedral_deg', float('nan')):>6.1f} "
              f"{e.get('surface_distance_mean_mm', float('nan')):>8.2f} "
              f"{e.get('surface_distance_p95_mm', float('nan')):>7.2f}")
    print(f"checks → {json_path}")
