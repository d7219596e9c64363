"""``tetdose import-dose``: other codes' per-phase doses onto the mesh, accumulated over phases.

Argument parsing and printing only: :func:`tetdose.coupling.import_dose.import_doses`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from tetdose.cli._common import add_calibration_arg, calibration_from, check_output
from tetdose.core.image import Image
from tetdose.core.io import read_ct, read_image
from tetdose.core.phase_names import order_by_names
from tetdose.coupling.dose_files import KINDS, dose_kind
from tetdose.coupling.export import exported_densities
from tetdose.coupling.import_dose import DEFAULT_UNIT, import_doses, write_imported
from tetdose.errors import OptionError
from tetdose.motion.phases import PhaseSeries


def add_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--phases", type=Path, required=True,
                   help="folder written by `tetdose deform` (phase VTUs with density + phases.pvd)")
    p.add_argument("--dose", type=Path, nargs="+", required=True, metavar="FILE",
                   help="one dose per phase (or one folder holding them), paired with the "
                        "phases by the phase number in the names (phase_020.0, 20%%, phase index "
                        "from 0) when they carry one, else in the given order: per-tet tally "
                        ".csv (tet or element, energy_mev or dose_gy, sigma), EGSnrc .3ddose, "
                        "DICOM RT Dose, .nrrd/.mha/.nii.gz")
    p.add_argument("--exported", type=Path,
                   help="the `tetdose export-phases` folder the code ran on: per-tet doses [Gy] "
                        "are turned into energy with its binned masses")
    body = p.add_mutually_exclusive_group()
    body.add_argument("--density", type=Path, nargs="+", metavar="IMAGE",
                      help="voxel doses: the density [g/cm³] image each phase's dose was "
                           "computed on (default: the phase mesh voxelized on the dose grid)")
    body.add_argument("--ct", type=Path, nargs="+", metavar="CT",
                      help="voxel doses: each phase's CT [HU] the dose was computed on (e.g. "
                           "the `tetdose 4dct` phases), turned into density by --calibration")
    add_calibration_arg(p)
    p.add_argument("--unit", default=DEFAULT_UNIT,
                   help=f"what the imported doses are (default {DEFAULT_UNIT!r})")
    p.add_argument("--dose-to", choices=("medium", "water"), default="medium",
                   help="what the imported doses are: dose to medium (default; Monte Carlo "
                        "codes score it) or dose to water; recorded in the outputs")
    p.add_argument("-o", "--output", type=Path, required=True, help="output folder")


def _dose_files(given: list[Path]) -> list[Path]:
    if len(given) != 1 or not given[0].is_dir():
        return given
    found = []
    for path in sorted(given[0].iterdir()):
        try:
            dose_kind(path)
        except OptionError:
            continue
        found.append(path)
    if not found:
        raise OptionError(f"{given[0]} holds no dose file ({', '.join(KINDS)}); give the files")
    return found


def _density_image(path: Path) -> Image:
    """A --density image, refused when its values are not densities [g/cm³] (negative, or
    beyond any material: a CT in HU given where densities are asked)."""
    from tetdose._checks import check_density
    from tetdose.core.calibration import MAX_DENSITY_G_CM3

    image = read_image(path)
    rho = check_density(image.array, what=f"voxels of --density {path}",
                        fix="give the density [g/cm³] the code ran on, or its CT with --ct")
    if rho.max() > MAX_DENSITY_G_CM3:
        raise OptionError(f"--density {path} holds values up to {rho.max():g}, denser than any "
                          "material: a CT in HU? give it with --ct (and --calibration)")
    return image


def run(args: argparse.Namespace) -> int:
    check_output(args, folder=True)
    series = PhaseSeries.read(None, args.phases)
    files = _dose_files(args.dose)
    if len(files) != series.n_phases:
        raise OptionError(f"{len(files)} dose files for {series.n_phases} phases; give one per "
                          "phase, in phase order")
    kinds = [dose_kind(f) for f in files]
    pct = series.phase_percent
    densities = ([_density_image(f) for f in order_by_names(args.density, pct, "--density")]
                 if args.density else None)
    if args.ct:
        cal = calibration_from(args)
        densities = [Image(cal.density_checked(ct.array)[0].astype(np.float64), ct.grid)
                     for ct in map(read_ct, order_by_names(args.ct, pct, "--ct"))]
    binned = (exported_densities(args.exported, series.reference.n_tets, series.phase_percent)
              if args.exported else None)
    result = import_doses(series, files, densities=densities, binned_densities=binned,
                          unit=args.unit, dose_to=args.dose_to)
    write_imported(result, args.output)
    print(f"{series.n_phases} phases imported ({', '.join(sorted(set(kinds)))}): accumulated "
          f"dose max {result.accumulated.dose_gy.max():.4g} {args.unit} (dose to "
          f"{args.dose_to}) → {args.output}")
    return 0
