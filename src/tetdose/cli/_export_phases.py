"""``tetdose export-phases``: breathing phases as TetGen/ICRP-145 or Abaqus meshes for other codes.

Argument parsing and printing only: :func:`tetdose.coupling.export.export_phases`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from tetdose.cli._common import check_output, int_at_least
from tetdose.coupling.binning import DEFAULT_MAX_MASS_ERROR
from tetdose.coupling.export import FORMATS, export_phases
from tetdose.motion.phases import PhaseSeries


def add_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--phases", type=Path, required=True,
                   help="folder written by `tetdose deform` (phase VTUs with density + phases.pvd)")
    p.add_argument("--format", choices=FORMATS, required=True,
                   help="tetgen: .node/.ele/.material per phase (ICRP 145 layout: Geant4, TOPAS, "
                        "PHITS); abaqus: .inp with one element set per material (MCNP6 "
                        "unstructured mesh) and the materials' m cards")
    p.add_argument("--density-bins", type=int_at_least(1), metavar="N",
                   help="at most N materials per phase (default: as few as keep the mass error "
                        f"≤ {100 * DEFAULT_MAX_MASS_ERROR:g} %%)")
    p.add_argument("--plan", type=Path,
                   help="plan.toml whose [materials] table gives region labels their material "
                        "(other tets get their density class, as in `tetdose dose`)")
    p.add_argument("-o", "--output", type=Path, required=True, help="output folder")


def run(args: argparse.Namespace) -> int:
    check_output(args, folder=True)
    series = PhaseSeries.read(None, args.phases)
    materials = compositions = None
    if args.plan is not None:
        from tetdose.plan.model import Plan

        plan = Plan.from_toml(args.plan)
        materials, compositions = dict(plan.materials), dict(plan.compositions)
    record = export_phases(series, args.output, fmt=args.format, n_bins=args.density_bins,
                           region_materials=materials, compositions=compositions)
    for ph in record["phases"]:  # type: ignore[union-attr]
        print(f"phase {ph['phase_percent']:5.1f} %: {ph['materials']} materials, mass "
              f"{ph['mass_g']:.6g} g, mass error {100 * ph['mass_error']:.3g} %, total mass "
              f"change {100 * ph['total_mass_change']:+.2g} %")
    print(f"{series.n_phases} phases ({record['n_tets']} tets each, lengths in cm; compositions "
          f"{', '.join(record['compositions'])}) → {args.output}")  # type: ignore[arg-type]
    return 0
