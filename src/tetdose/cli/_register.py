"""``tetdose register``: one displacement field per phase of a real 4D-CT (reference → phase).

Writes ``phase_PPP.P.nrrd`` (mm, ITK convention, read by ``deform --dvf``) per phase and
``register.json`` (settings, and per phase: file, percent and the quality report). A field that
folds (det J ≤ 0 inside the mask) is still written, for inspection, but reported as an error and
the exit code is 2.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from tetdose.motion.register import RegistrationReport, RegistrationSettings

def add_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--4dct", dest="ct4d", required=True, type=Path, nargs="+", metavar="CT4D",
                   help="4D-CT: a folder of phase CT series, or one image file per phase")
    p.add_argument("--reference", required=True, type=float, metavar="PERCENT",
                   help="reference phase [%%] (the CT the mesh was mapped from)")
    p.add_argument("-o", "--output", required=True, type=Path, help="output folder for the fields")
    add_registration_args(p)


def add_registration_args(p: argparse.ArgumentParser) -> None:
    """Options shared with ``deform --4dct``."""
    from tetdose.cli._common import float_in, int_at_least
    from tetdose.motion.register import METHODS, RegistrationSettings

    d = RegistrationSettings()
    p.add_argument("--mask", type=Path,
                   help="registration mask: a label image, register inside its non-zero voxels "
                   "(default: the body, HU > -400, slice-wise convex hull)")
    p.add_argument("--registration", dest="reg_method", choices=METHODS, default=d.method,
                   help="symmetric-forces demons (default: measured faster and more accurate) or B-spline")
    p.add_argument("--smoothing-mm", type=float_in(0.0, low_open=True), default=d.smoothing_mm,
                   help="demons: Gaussian σ of the field [mm]")
    p.add_argument("--grid-spacing-mm", type=float_in(0.0, low_open=True),
                   default=d.grid_spacing_mm,
                   help="B-spline: control-point spacing at the finest level [mm]")
    p.add_argument("--shrink", type=int_at_least(1), nargs="+", default=list(d.shrink),
                   help="pyramid shrink factors, coarse → fine")
    p.add_argument("--iterations", type=int_at_least(1), nargs="+", default=list(d.iterations),
                   help="iterations per pyramid level")
    p.add_argument("--threads", type=int_at_least(1), help="SimpleITK threads (default: all cores)")
    p.add_argument("--crop-margin-mm", type=float_in(0.0), default=d.crop_margin_mm,
                   help="demons: register inside the masks' bounding box widened by this "
                   "margin [mm] (the field is continued outside it by its edge values)")
    p.add_argument("--no-crop", action="store_true",
                   help="demons: register the whole image, not the masks' bounding box")
    p.add_argument("--no-warm-start", action="store_true",
                   help="demons: start every phase from zero, not from its neighbour's field "
                   "(phases are otherwise registered outward from the reference)")
    p.add_argument("--inverse-consistency", action="store_true",
                   help="also register phase → reference and report ‖u(x) + w(x + u(x))‖ (2× time)")


def settings_from(args: argparse.Namespace) -> RegistrationSettings:
    from tetdose.motion.register import RegistrationSettings

    return RegistrationSettings(method=args.reg_method, shrink=tuple(args.shrink),
                                iterations=tuple(args.iterations), smoothing_mm=args.smoothing_mm,
                                grid_spacing_mm=args.grid_spacing_mm, threads=args.threads,
                                crop_margin_mm=None if args.no_crop else args.crop_margin_mm,
                                warm_start=not args.no_warm_start)


def register_to(args: argparse.Namespace, out_dir: Path) -> tuple[list[Path], list[float],
                                                                 list[RegistrationReport]]:
    """The options' 4D-CT registered into ``out_dir`` (:func:`~tetdose.motion.dvf_folder.
    register_to_folder`)."""
    from tetdose.motion.dvf_folder import register_to_folder

    return register_to_folder(ct4d_source(args.ct4d), args.reference, out_dir, mask=args.mask,
                              settings=settings_from(args),
                              inverse_consistency=args.inverse_consistency,
                              progress=not args.quiet)


def ct4d_source(paths: list[Path]) -> Path | list[Path]:
    """``--4dct`` values: one folder (or file), or several image files (one per phase)."""
    return paths[0] if len(paths) == 1 else paths


def print_reports(reports: list[RegistrationReport], command: str) -> int:
    """Print one line per phase; folding phases as errors. Return the exit code."""
    import sys

    code = 0
    for r in reports:
        print(r.line())
        if r.folded:
            print(f"tetdose {command}: error: {r.folding_message()}", file=sys.stderr)
            code = 2
    return code


def run(args: argparse.Namespace) -> int:
    from tetdose._atomic import atomic_write_dir
    from tetdose.motion.dvf_folder import REPORT_NAME

    with atomic_write_dir(args.output) as tmp:
        files, _, reports = register_to(args, Path(tmp))
    code = print_reports(reports, "register")
    print(f"wrote {len(files)} displacement fields and {REPORT_NAME} to {args.output}")
    return code
