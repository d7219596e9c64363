"""Argument helpers shared by the subcommands."""

from __future__ import annotations

import argparse

from tetdose.calibration import HUCalibration
from tetdose.errors import MeshError
from tetdose.io import read_mesh
from tetdose.mesh import TetMesh


def add_calibration_arg(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--calibration", metavar="CSV",
                        help="HU → density curve (columns HU, g/cm³); default Schneider 2000")


def calibration_from(args: argparse.Namespace) -> HUCalibration:
    return HUCalibration.from_csv(args.calibration) if args.calibration else \
        HUCalibration.schneider2000()


def read_mapped_mesh(path: str) -> TetMesh:
    """A mesh that carries point_data ``density`` [g/cm³] (the output of ``tetdose map``)."""
    mesh = read_mesh(path)
    if "density" not in mesh.point_data:
        raise MeshError(f"{path} has no point_data 'density'; run `tetdose map` first")
    return mesh
