"""``tetdose compare`` (mesh vs voxel dose report; or two doses of one kind with ``--dose`` and
``--reference-dose``, :mod:`tetdose.compare.same_kind`) and ``tetdose export-dose`` (RT Dose).

Both subcommands live here; ``add_args`` tells them apart by the subparser's name. Argument
parsing and printing only: the comparison is :func:`tetdose.compare.comparison.compare_doses`
(gamma where both doses exist: voxels at least half inside the mesh), the export
:func:`tetdose.core.transfer.dose_on_grid` and :func:`tetdose.dicom.rt_dose.write_rt_dose`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from tetdose.cli._common import (
    add_calibration_arg,
    calibration_from,
    check_output,
    float_in,
    int_at_least,
)
from tetdose.errors import OptionError, TetdoseError

MESH_SUFFIXES = (".vtu", ".vtk", ".xdmf", ".msh")


def add_args(parser: argparse.ArgumentParser) -> None:
    command = parser.prog.split()[-1]
    parser.set_defaults(_compare_command=command)
    if command == "export-dose":
        parser.add_argument("--dose", required=True, type=Path,
                            help="dose.vtu (cell_data dose: Gy per fraction when prescribed, "
                                 "else Gy per source photon) or a dose image (.nrrd, .mha …)")
        parser.add_argument("--like", required=True, type=Path,
                            help="the CT (DICOM folder, or image) whose grid the RT Dose uses")
        parser.add_argument("-o", "--output", required=True, type=Path, help="rtdose.dcm")
        parser.add_argument("--bits", type=int, choices=(16, 32), default=16)
        _add_dose_to(parser)
        return
    parser.add_argument("--mesh-dose", type=Path,
                        help="dose VTU (cell_data dose; dose_std: its σ) or a folder holding "
                             "accumulated.vtu")
    parser.add_argument("--voxel-dose", type=Path,
                        help="dose image (.nrrd …; its σ: the _std image beside it, dose_std.nrrd for "
                             "dose.nrrd) or a folder holding accumulated.nrrd")
    parser.add_argument("--dose", type=Path,
                        help="instead of --mesh-dose/--voxel-dose: a dose of the same kind as "
                             "--reference-dose (two images on one grid, or two VTUs of one mesh "
                             "topology: phase vs phase, tetdose vs an imported dose)")
    parser.add_argument("--reference-dose", type=Path, help="the reference for --dose")
    parser.add_argument("--structures", type=Path,
                        help="label image (0 = background) or a DICOM RTSTRUCT file")
    parser.add_argument("--ct", type=Path,
                        help="the CT of the voxel dose (on its grid): the body outline and the "
                             "tissue compared (density ≥ 0.2 g/cm³; never air), the voxel "
                             "regions' masses for the DVH table (default: estimated from the "
                             "mesh's densities)")
    add_calibration_arg(parser)
    parser.add_argument("--reference", choices=("voxel", "mesh"), default="voxel",
                        help="which dose is the gamma reference (default voxel)")
    parser.add_argument("--threshold", type=float_in(0.0, 100.0, high_open=True), default=10.0,
                        help="gamma low-dose threshold [%% of the reference maximum]")
    parser.add_argument("--gamma", action="append", type=_criterion, metavar="DD/DTA[/local]",
                        help="a gamma criterion, dose %% / distance mm, e.g. 3/3 or 3/3/local "
                             "(repeatable; default 3/3, 2/2 and 3/3/local)")
    parser.add_argument("--gamma-max-points", type=int_at_least(1), default=200_000,
                        help="evaluate gamma on a seeded random sample of at most this many "
                             "points above the threshold (pass rate ± its standard error)")
    _add_dose_to(parser)
    parser.add_argument("-o", "--output", required=True, type=Path, help="report folder")


def _criterion(text: str) -> tuple[float, float, bool]:
    parts = text.split("/")
    try:
        if len(parts) not in (2, 3) or (len(parts) == 3 and parts[2] != "local"):
            raise ValueError
        return float(parts[0]), float(parts[1]), len(parts) == 3
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is no gamma criterion; write e.g. 3/3 or "
                                         "3/3/local") from None


def _add_dose_to(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--dose-to", choices=("medium", "water"), default=None,
                        help="the dose the inputs must be (default: what their run records "
                             "say; a file without a record is dose to medium); a mismatch is "
                             "refused: run `tetdose dose --dose-to water` to get dose to water")


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


def _run_compare(args: argparse.Namespace) -> int:
    pair = (args.dose is not None, args.reference_dose is not None)
    mixed = (args.mesh_dose is not None, args.voxel_dose is not None)
    if pair == (True, True) and mixed == (False, False):
        return _run_same_kind(args)
    if mixed != (True, True) or any(pair):
        raise OptionError("give --mesh-dose and --voxel-dose (a mesh dose against a voxel "
                          "dose), or --dose and --reference-dose (two doses of one kind)")
    return _run_mesh_voxel(args)


def _run_same_kind(args: argparse.Namespace) -> int:
    from tetdose.compare.comparison import read_mesh_dose, read_structure_masks, recorded_dose_unit
    from tetdose.compare.consistency import mesh_dose_std, read_dose_std_image
    from tetdose.compare.report import write_report
    from tetdose.compare.same_kind import compare_images, compare_meshes
    from tetdose.core.io import read_ct, read_image
    from tetdose.meshing.labels import body_mask

    check_output(args, folder=True)
    unit = recorded_dose_unit(args.dose)
    kinds = [p.suffix.lower() in MESH_SUFFIXES for p in (args.dose, args.reference_dose)]
    if kinds[0] != kinds[1]:
        raise OptionError("--dose and --reference-dose are of different kinds (a mesh and an "
                          "image); use --mesh-dose and --voxel-dose for those")
    if kinds[0]:
        (ma, da), (mb, db) = read_mesh_dose(args.dose), read_mesh_dose(args.reference_dose)
        figures, summary = compare_meshes(ma, da, mesh_dose_std(ma), mb, db, mesh_dose_std(mb),
                                          threshold_percent=args.threshold, unit=unit)
    else:
        a, b = read_image(args.dose), read_image(args.reference_dose)
        density = body = None
        if args.ct is not None:
            ct = read_ct(args.ct)
            density = ct.with_array(calibration_from(args).density(ct.array).astype(float))
            body = body_mask(ct.array)
        masks = read_structure_masks(args.structures, b.grid) if args.structures else None
        figures, summary = compare_images(
            a, read_dose_std_image(args.dose, a.grid), b,
            read_dose_std_image(args.reference_dose, b.grid), structures=masks, density=density,
            body=body, threshold_percent=args.threshold, gamma_max_points=args.gamma_max_points,
            unit=unit)
    write_report(args.output, figures, summary)
    print(f"compared: {summary['region']['description']}")
    print(f"σ: dose {summary['uncertainty']['dose']}; reference "
          f"{summary['uncertainty']['reference']}")
    for name, row in summary["structures"].items():
        print(_significance_line(name, row))
    for name, g in summary.get("gamma", {}).items():
        print(f"gamma {name}: {g['pass_rate_percent']:.2f} % pass (two unbiased runs of these "
              f"σ: {g['expected_pass_rate_percent']:.1f} %)")
    print(f"report → {args.output / 'report.html'}")
    return 0


def _run_mesh_voxel(args: argparse.Namespace) -> int:
    from tetdose.compare.comparison import (
        compare_doses,
        read_mesh_dose,
        read_structure_masks,
        recorded_dose_unit,
    )
    from tetdose.compare.consistency import mesh_dose_std, read_dose_std_image
    from tetdose.core.io import read_ct, read_image
    from tetdose.dose.dose_to import recorded_dose_to, require_same
    from tetdose.meshing.labels import body_mask

    check_output(args, folder=True)
    mesh_path = _find(args.mesh_dose, "accumulated", MESH_SUFFIXES, "mesh")
    mesh, dose = read_mesh_dose(mesh_path)
    voxel_path = _find(args.voxel_dose, "accumulated", (".nrrd", ".mha", ".nii.gz"),
                       "dose image")
    voxel = read_image(voxel_path)
    dose_to = require_same(args.dose_to, recorded_dose_to(mesh_path, mesh), f"{mesh_path}")
    require_same(dose_to, recorded_dose_to(voxel_path), f"{voxel_path}")
    masks = read_structure_masks(args.structures, voxel.grid) if args.structures else None
    density = body = None
    if args.ct is not None:
        ct = read_ct(args.ct)
        density = ct.with_array(calibration_from(args).density_checked(
            ct.array, f"the CT {args.ct}")[0].astype(float))
        body = body_mask(ct.array)
    result = compare_doses(mesh, dose, voxel, structures=masks, reference=args.reference,
                           threshold_percent=args.threshold,
                           gamma_max_points=args.gamma_max_points,
                           **({"criteria": tuple(args.gamma)} if args.gamma else {}),
                           unit=recorded_dose_unit(mesh_path), density=density,
                           mesh_std=mesh_dose_std(mesh),
                           voxel_std=read_dose_std_image(voxel_path, voxel.grid), body=body)
    result.summary["dose_to"] = dose_to
    result.write(args.output)
    s = result.summary
    reg = s["region"]
    print(f"compared: {reg['voxels']} voxels ({reg['volume_cm3']:.1f} cm³), "
          f"{reg['description']}")
    print(f"σ: mesh {s['uncertainty']['mesh']}; voxel {s['uncertainty']['voxel']}")
    for name, row in s["structures"].items():
        print(_significance_line(name, row))
    for name, g in s["gamma"].items():
        print(f"gamma {name}: {g['pass_rate_percent']:.2f} % pass (two unbiased runs of these "
              f"σ: {g['expected_pass_rate_percent']:.1f} %)")
    for name, row in s["dvh"].items():
        print(_dvh_line(name, row))
    print(f"report → {args.output / 'report.html'}")
    return 0


def _significance_line(name: str, row: dict) -> str:
    """Mean relative difference ± 1σ and the systematic part of one structure."""
    line = (f"{name}: mean difference {100 * row['mean_rel_diff']:+.2f} ± "
            f"{100 * row['mean_rel_diff_sigma']:.2f} %")
    if row.get("systematic_rel_diff") is None:
        return f"{line}; {row['systematic_model']}"
    model = row["systematic_model"]
    if model == "none":
        return (f"{line}; statistically consistent (systematic "
                f"{100 * row['systematic_rel_diff']:+.2f} ± "
                f"{100 * row['systematic_rel_diff_sigma']:.2f} %, carried by no point)")
    return (f"{line}; systematic {100 * row['systematic_rel_diff']:+.2f} ± "
            f"{100 * row['systematic_rel_diff_sigma']:.2f} % in "
            f"{100 * row['systematic_fraction']:.0f} % of the points")


def _dvh_line(name: str, row: dict) -> str:
    """One line per DVH: each side's region (volume, mass) and means, and the region note."""
    def side(what: str, d: dict) -> str:
        mass = f", {d['mass_g']:.4g} g" if "mass_g" in d else ""
        by_mass = f" (by mass {d['Dmean_mass_weighted']:.4g})" if "Dmean_mass_weighted" in d \
            else ""
        return f"{what} {d['volume_cm3']:.4g} cm³{mass}: mean {d['Dmean']:.4g}{by_mass}"

    note = f"; note: {row['note']}" if "note" in row else ""
    flagged = [k for k, p in row.get("points", {}).items() if p["significant"]]
    if flagged:
        note += f"; beyond 2σ: {', '.join(flagged)}"
    return f"DVH {name}: {side('tets', row['mesh'])}; {side('voxels', row['voxel'])}{note}"


def _run_export(args: argparse.Namespace) -> int:
    from tetdose.compare.comparison import read_mesh_dose, recorded_dose_unit
    from tetdose.core.io import read_image
    from tetdose.core.transfer import dose_on_grid
    from tetdose.dicom.rt_dose import DOSE_UNITS, write_rt_dose
    from tetdose.dose.dose_to import recorded_dose_to, require_same

    check_output(args, suffixes=(".dcm",))
    unit = recorded_dose_unit(args.dose)
    if unit not in DOSE_UNITS:
        raise OptionError(
            f"{args.dose}: its record says the dose is in {unit!r}, which an RT Dose cannot "
            f"hold (Gy, Gy per fraction: absolute; Gy per source photon/particle: relative); "
            "re-run import-dose --unit 'Gy per fraction' (or 'Gy') if the doses are absolute, "
            "or without --unit (relative, per source particle)")
    grid = read_image(args.like).grid
    mesh = None
    if args.dose.suffix.lower() in MESH_SUFFIXES:
        mesh, per_tet = read_mesh_dose(args.dose)
        img = dose_on_grid((mesh, per_tet), grid)
    else:
        img = dose_on_grid(read_image(args.dose), grid, what=str(args.dose))
    dose_to = require_same(args.dose_to, recorded_dose_to(args.dose, mesh), str(args.dose))
    reference = args.like if args.like.is_dir() else None
    write_rt_dose(img, args.output, reference_ct=reference, bits=args.bits, unit=unit,
                  dose_to=dose_to)
    relative = (" (DoseUnits RELATIVE: not absolute; a [prescription] or [calibration] in the "
                "plan gives Gy per fraction)" if DOSE_UNITS[unit] == "RELATIVE" else "")
    print(f"RT Dose {grid.size}, max {img.array.max():.4g} {unit}{relative}, dose to {dose_to} "
          f"→ {args.output}")
    return 0
