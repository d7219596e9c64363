"""``tetdose map``: vertex densities [g/cm³] of a tetrahedral mesh from a CT."""

from __future__ import annotations

import argparse

from tetdose._checks import check_density
from tetdose.cli._common import (
    add_calibration_arg,
    add_output_args,
    calibration_from,
    check_output,
    int_at_least,
)
from tetdose.core.io import MESH_SUFFIXES, read_ct, read_mesh, write_mesh
from tetdose.core.overlap import METHODS
from tetdose.mapping import SOLVERS, map_density


def add_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--ct", required=True, help="CT: DICOM series folder, NRRD, MHA or NIfTI (HU)")
    p.add_argument("--mesh", required=True, help="tetrahedral mesh (VTU, MSH, INP, MESH, ELE …)")
    add_output_args(p, "output mesh (.vtu recommended)", folder=False)
    p.add_argument("--solver", choices=SOLVERS, default="l2",
                   help="l2: mass-conserving projection (default); lsq: the paper's eq. 9")
    p.add_argument("--overlap", choices=METHODS, default="exact",
                   help="tet∩voxel volumes: exact (default) or the paper's Monte Carlo")
    p.add_argument("--samples", type=int_at_least(1), default=1000,
                   help="points per tet for monte-carlo (≥ 1; default 1000)")
    p.add_argument("--by-region", action="store_true",
                   help="duplicate vertices per region so density may jump between regions")
    p.add_argument("--fix-orientation", action="store_true",
                   help="swap two vertices of inverted tetrahedra instead of refusing them")
    add_calibration_arg(p)


def run(args: argparse.Namespace) -> int:
    check_output(args, suffixes=MESH_SUFFIXES)
    mesh = read_mesh(args.mesh, fix_orientation=args.fix_orientation)
    ct = read_ct(args.ct)
    dm = map_density(mesh, ct, calibration=calibration_from(args), solver=args.solver,
                     overlap=args.overlap, n_samples=args.samples, by_region=args.by_region,
                     progress=not args.quiet)
    rho = check_density(dm.density_g_cm3, what="vertex densities", negative="warn",
                        fix="the paper's least squares undershoots at sharp edges, and "
                            "voxelize/evaluate refuse such a mesh: use --solver l2")
    write_mesh(args.output, dm.mesh)
    print(f"mapped {mesh.n_tets} tetrahedra, {dm.mesh.n_points} vertices ({args.solver}): density "
          f"{rho.min():.4g}…{rho.max():.4g} g/cm³, mesh mass {dm.mesh_mass_g:.6g} g, CT mass in "
          f"mesh {dm.ct_mass_covered_g:.6g} g (rel. diff. {dm.mass_error_covered:.2e}) → "
          f"{args.output}")
    return 0
