"""``tetdose deform`` (breathing phases with mass-conserving density) and ``tetdose 4dct``.

Both subcommands live here; ``add_args`` tells them apart by the subparser's name (the last
word of ``parser.prog``) and records it for ``run``. Argument parsing and printing only: the
motion source and the mass report are :mod:`tetdose.motion.source`, the virtual 4D-CT
:mod:`tetdose.motion.ct4d`.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from tetdose._atomic import atomic_write_dir
from tetdose.cli._common import density_or_word, float_in, int_at_least, read_mapped_mesh

if TYPE_CHECKING:
    from tetdose.core.mesh import TetMesh
    from tetdose.motion import PhaseSeries


def add_args(parser: argparse.ArgumentParser) -> None:
    command = parser.prog.split()[-1]
    parser.set_defaults(_motion_command=command)
    if command == "deform":
        _add_deform_args(parser)
    else:
        _add_4dct_args(parser)


def run(args: argparse.Namespace) -> int:
    return _run_deform(args) if args._motion_command == "deform" else _run_4dct(args)


def _add_deform_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--mesh", required=True, type=Path,
                   help="reference mesh with point_data 'density' (from `tetdose map`)")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--phases", nargs="+", type=Path, metavar="VTU",
                     help="phase meshes: the reference's cells on moved points")
    src.add_argument("--dvf", nargs="+", type=Path, metavar="IMAGE",
                     help="displacement fields (mm, reference → phase), one per phase")
    src.add_argument("--surfaces", nargs="+", type=Path, metavar="SURFACE",
                     help="target surfaces (STL/OBJ/PLY), one per phase: ICP + elastic FEM")
    src.add_argument("--breathing", action="store_true",
                     help="built-in Lujan cos^2n breathing (reference = end-exhale)")
    src.add_argument("--4dct", dest="ct4d", type=Path, nargs="+", metavar="CT4D",
                     help="real 4D-CT: register every phase to --reference, then deform")
    p.add_argument("--reference", type=float, metavar="PERCENT",
                   help="--4dct: reference phase [%%], the CT the mesh was mapped from")
    p.add_argument("--amplitude-mm", type=float_in(0.0), default=10.0,
                   help="breathing: cranio-caudal amplitude at the diaphragm [mm]")
    p.add_argument("--period-s", type=float_in(0.0, low_open=True), default=4.0,
                   help="breathing: period [s]")
    p.add_argument("--n-phases", type=int_at_least(1), default=10,
                   help="breathing: number of phases")
    p.add_argument("--shape-n", type=int_at_least(1), default=3,
                   help="breathing: exponent n of cos^2n")
    p.add_argument("--lung-regions", nargs="+", type=int, metavar="LABEL",
                   help="breathing: the mesh regions that are lung and change volume (default: "
                   "regions of mean density < 0.5 g/cm³); all other tissue keeps its volume")
    p.add_argument("--phase-percent", nargs="+", type=float_in(0.0, 100.0),
                   help="phase positions in the cycle [%%] (default 100·k/K)")
    p.add_argument("--method", choices=("l2", "lsq"), default="l2",
                   help="density update: mass-conserving L2 projection or the paper's LSQ")
    p.add_argument("--increments", type=int_at_least(1), default=4, help="FEM load increments")
    p.add_argument("--young-kpa", type=float_in(0.0, low_open=True), default=7.8,
                   help="FEM Young's modulus [kPa]")
    p.add_argument("--poisson", type=float_in(0.0, 0.4999), default=0.45,
                   help="FEM Poisson's ratio")
    p.add_argument("-o", "--output", required=True, type=Path,
                   help="output folder: one VTU per phase + phases.pvd + mass_report.csv + "
                   "volume_report.csv (ΔV/V per region) "
                   "(with --4dct also dvf/: the fields and register.json)")
    from tetdose.cli._register import add_registration_args

    add_registration_args(p)


def _add_4dct_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--phases", required=True, type=Path, help="folder written by `deform`")
    p.add_argument("--like", required=True, type=Path,
                   help="reference CT (DICOM folder or image file): grid and outside tissue")
    p.add_argument("-o", "--output", required=True, type=Path, help="output folder")
    p.add_argument("--format", choices=("dicom", "nrrd"), default="dicom")
    p.add_argument("--background", default="ct", type=density_or_word(("ct", "air")),
                   help="outside the mesh: 'ct' (reference CT), 'air' or a density [g/cm³]")
    p.add_argument("--dvf", nargs="+", type=Path, metavar="IMAGE",
                   help="one DVF per phase: also warp the CT outside the mesh")
    p.add_argument("--partial", choices=("mass", "extrapolate"), default="mass",
                   help="voxels partly inside the mesh (see tetdose.core.voxelize)")


def _motion_series(args: argparse.Namespace, reference: TetMesh, out_dir: Path) -> PhaseSeries:
    """The source the options name (``--4dct``: registered into ``out_dir/dvf`` first)."""
    from tetdose.cli._register import print_reports, register_to
    from tetdose.core.phase_names import percents_from_names
    from tetdose.errors import OptionError, TetdoseError
    from tetdose.motion import BreathingModel
    from tetdose.motion.dvf_folder import percents_of
    from tetdose.motion.source import FemOptions, check_reference, phase_series

    pct = args.phase_percent
    dvfs = args.dvf
    if args.lung_regions and not args.breathing:
        raise OptionError("--lung-regions applies to --breathing only; the other motion sources "
                          "bring their own motion")
    if args.ct4d:
        if args.reference is None:
            raise OptionError("--4dct needs --reference PERCENT: the phase the mesh was mapped "
                              "from")
        check_reference(reference)  # before the registration's minutes
        dvfs, percents, reports = register_to(args, out_dir / "dvf")
        if print_reports(reports, "deform"):
            raise TetdoseError("a registered field folds (see above); the mesh was not deformed — "
                               "raise --smoothing-mm or give a --mask")
        pct = percents if pct is None else pct
    elif dvfs and pct is None:
        pct = percents_of(list(dvfs))
    phases = args.phases
    if pct is None and dvfs and not args.ct4d:
        dvfs, pct = percents_from_names(dvfs, "--dvf")
    elif pct is None and phases:
        phases, pct = percents_from_names(phases, "--phases")
    surfaces = args.surfaces
    if pct is None and surfaces:
        surfaces, pct = percents_from_names(surfaces, "--surfaces")
    breathing = (BreathingModel(args.amplitude_mm, args.period_s, args.shape_n)
                 if args.breathing else None)
    return phase_series(reference, phases=phases, dvfs=dvfs, surfaces=surfaces,
                        breathing=breathing, n_phases=args.n_phases, phase_percent=pct,
                        fem=FemOptions(args.increments, args.young_kpa, args.poisson),
                        lung_regions=args.lung_regions)


def _run_deform(args: argparse.Namespace) -> int:
    from tetdose.motion.source import deform, mass_report_csv, volume_report_csv

    reference = read_mapped_mesh(args.mesh)
    with atomic_write_dir(args.output) as tmp:
        series, reports = deform(_motion_series(args, reference, tmp), method=args.method)
        series.write(tmp)
        (tmp / "mass_report.csv").write_text(mass_report_csv(series, reports))
        (tmp / "volume_report.csv").write_text(volume_report_csv(reports))
    for r in reports:
        print(r.line())
    print(f"wrote {series.n_phases} phases ({args.method}) to {args.output}")
    return 0


def _run_4dct(args: argparse.Namespace) -> int:
    from tetdose.cli._common import check_output
    from tetdose.core.io import read_ct, read_image
    from tetdose.core.phase_names import order_by_names
    from tetdose.motion import PhaseSeries, read_dvf
    from tetdose.motion.ct4d import virtual_4dct, write_4dct

    check_output(args, folder=True)
    series = PhaseSeries.read(None, args.phases)
    dvfs = None if args.dvf is None else [
        read_dvf(f) for f in order_by_names(args.dvf, series.phase_percent, "--dvf")]
    ct = read_ct(args.like) if args.background == "ct" or dvfs else read_image(args.like)
    images = virtual_4dct(series, ct, background=args.background, dvfs=dvfs, partial=args.partial,
                          progress=not args.quiet)
    out = write_4dct(images, args.output, phase_percent=series.phase_percent, fmt=args.format,
                     reference=args.like)
    print(f"wrote {len(out)} phases ({args.format}) to {args.output}")
    return 0
