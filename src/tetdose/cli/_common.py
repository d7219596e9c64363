"""Argument helpers shared by the subcommands."""

from __future__ import annotations

import argparse

from tetdose.calibration import HUCalibration


def add_calibration_arg(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--calibration", metavar="CSV",
                        help="HU → density curve (columns HU, g/cm³); default Schneider 2000")


def calibration_from(args: argparse.Namespace) -> HUCalibration:
    return HUCalibration.from_csv(args.calibration) if args.calibration else \
        HUCalibration.schneider2000()
