"""``tetdose phantom NAME -o DIR``: write a seeded procedural phantom (CT, labels, mesh)."""

from __future__ import annotations

import argparse

from tetdose._atomic import atomic_write_dir
from tetdose.cli._common import add_output_args, check_output, int_at_least
from tetdose.phantoms import MESHERS, PHANTOMS, SIZES, make_phantom, write_phantom


def add_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("name", choices=PHANTOMS, help="which phantom")
    add_output_args(parser, "output folder: ct.nrrd (HU), labels.nrrd, mesh.vtu, phantom.json",
                    folder=True, metavar="DIR")
    parser.add_argument("--seed", type=int_at_least(0), default=0,
                        help="random seed, a whole number ≥ 0 (default 0)")
    parser.add_argument("--size", choices=SIZES, default="medium",
                        help="small (tests, a few thousand tets) or medium (demo; default)")
    parser.add_argument("--mesher", choices=MESHERS, default="organ",
                        help="organ (default): one conforming organ-shaped mesh (MMG, "
                             "tetdose[meshing]); structured: staircase Kuhn grid on exact planes")


def run(args: argparse.Namespace) -> int:
    out = check_output(args, folder=True)
    phantom = make_phantom(args.name, seed=args.seed, size=args.size, mesher=args.mesher)
    with atomic_write_dir(out) as tmp:  # all four files or none; the folder replaced as a whole
        write_phantom(phantom, tmp)
    grid = phantom.ct.grid
    print(f"{args.name} (seed {args.seed}, {args.size}): CT {grid.size[0]}×{grid.size[1]}×"
          f"{grid.size[2]} at {grid.spacing_mm[0]:g} mm, mesh {phantom.mesh.n_tets} tets / "
          f"{phantom.mesh.n_points} points → {args.output}")
    return 0
