"""Argument helpers shared by the subcommands: typed options checked at parse time, the output
option with ``--overwrite``, and inputs read with their checks."""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable, Sequence
from pathlib import Path

from tetdose._atomic import check_not_input, check_output_dir, check_output_file
from tetdose._checks import check_density
from tetdose.core.calibration import MAX_DENSITY_G_CM3, HUCalibration
from tetdose.core.io import read_mesh
from tetdose.core.mesh import TetMesh
from tetdose.errors import MeshError, OutputError


def add_calibration_arg(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--calibration", metavar="CSV",
                        help="HU → density curve (columns HU, g/cm³); default Schneider 2000")


def calibration_from(args: argparse.Namespace) -> HUCalibration:
    return HUCalibration.from_csv(args.calibration) if args.calibration else \
        HUCalibration.schneider2000()


def add_output_args(parser: argparse.ArgumentParser, help_text: str, *, folder: bool,
                    metavar: str | None = None) -> None:
    """``-o/--output`` (required) and, for a folder, ``--overwrite``."""
    parser.add_argument("-o", "--output", required=True, metavar=metavar, help=help_text)
    if folder:
        parser.add_argument("--overwrite", action="store_true",
                            help="replace the output folder even if tetdose did not write it")


def check_output(args: argparse.Namespace, *, suffixes: Sequence[str] | None = None,
                 folder: bool = False) -> Path:
    """Validate ``args.output`` before any work (extension, not an input, writable, and for a
    folder: not a foreign folder unless ``--overwrite``); see :mod:`tetdose._atomic`."""
    if folder:
        return check_output_dir(args.output, force=bool(getattr(args, "overwrite", False)),
                                what="-o folder")
    return check_output_file(args.output, suffixes=suffixes, what="-o")


#: Commands whose ``-o`` is a file (the others write a folder).
FILE_OUTPUTS = ("map", "voxelize", "dose", "export-dose", "mesh")


def output_files(args: argparse.Namespace, module: object = None) -> list[Path]:
    """The files a command writes: ``-o`` first, then those its module's ``output_files(args)``
    names beside it (``dose``: images and the JSON record; ``mesh``: the checks JSON); ``[]``
    without ``-o``."""
    output = getattr(args, "output", None)
    if output is None or not str(output):
        return []
    more = getattr(module, "output_files", None)
    files = [Path(output), *(more(args) if callable(more) else [])]
    return list(dict.fromkeys(files))


def check_outputs_first(args: argparse.Namespace, module: object = None) -> None:
    """Before any work: no output of the command (see :func:`output_files`) is, holds or lies
    inside one of its inputs, and the files it writes beside ``-o`` can be written (see
    :mod:`tetdose._atomic`)."""
    files = output_files(args, module)
    for i, path in enumerate(files):
        if i == 0:
            if args.command in FILE_OUTPUTS:
                check_output_file(path, what="-o")
            else:
                check_not_input(path, what="-o")
            continue
        try:
            check_output_file(path, what="that file")
        except OutputError as exc:
            raise OutputError(f"-o {files[0]} also writes {path.name} beside it, and {exc}"
                              ) from exc


def int_at_least(low: int) -> Callable[[str], int]:
    """argparse type: a whole number ≥ ``low``."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a whole number ≥ {low}, got {text!r}"
                                             ) from None
        if value < low:
            raise argparse.ArgumentTypeError(f"must be a whole number ≥ {low}, got {value}")
        return value

    parse.__name__ = f"int ≥ {low}"
    return parse


#: Largest --histories accepted: every whole number up to 2**53 is exact in float64.
MAX_HISTORIES = 2**53


def count(text: str) -> int:
    """argparse type: a whole number ≥ 1 written as an integer or a float (``1e7``), at most
    :data:`MAX_HISTORIES` (NaN, infinity and fractions refused)."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value) or value != int(value) or not 1 <= value <= MAX_HISTORIES:
        raise argparse.ArgumentTypeError(
            f"expected a whole number from 1 to {MAX_HISTORIES:.3g} (e.g. 1e6), got {text!r}")
    return int(value)


def float_in(low: float, high: float = math.inf, *, low_open: bool = False,
             high_open: bool = False) -> Callable[[str], float]:
    """argparse type: a finite number in [low, high]; ``low_open``/``high_open`` exclude the
    ends."""
    left, right = "(" if low_open else "[", ")" if high_open else "]"
    span = f"> {low:g}" if high == math.inf and low_open else f"≥ {low:g}" \
        if high == math.inf else f"in {left}{low:g}, {high:g}{right}"

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if not math.isfinite(value) or value < low or value > high or \
                (low_open and value == low) or (high_open and value == high):
            raise argparse.ArgumentTypeError(f"expected a finite number {span}, got {text!r}")
        return value

    parse.__name__ = f"number {span}"
    return parse


def density_or_word(words: Sequence[str]) -> Callable[[str], str | float]:
    """argparse type: one of ``words`` or a finite density ≥ 0 [g/cm³]."""

    def parse(text: str) -> str | float:
        if text.strip().lower() in words:
            return text.strip().lower()
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"expected {', '.join(words)} or a density in g/cm³, got {text!r}") from None
        if not math.isfinite(value) or value < 0:
            raise argparse.ArgumentTypeError(f"a density must be a finite number ≥ 0 g/cm³, "
                                             f"got {text!r}")
        if value > MAX_DENSITY_G_CM3:
            raise argparse.ArgumentTypeError(
                f"{text} g/cm³ is denser than any material (osmium 22.6 g/cm³): a CT number in "
                "HU? give the density in g/cm³ (water 1.0)")
        return value

    parse.__name__ = "background"
    return parse


def read_mapped_mesh(path: str) -> TetMesh:
    """A mesh that carries point_data ``density`` [g/cm³] (the output of ``tetdose map``),
    finite and non-negative."""
    mesh = read_mesh(path)
    if "density" not in mesh.point_data:
        raise MeshError(f"{path} has no point_data 'density'; run `tetdose map` first")
    check_density(mesh.point_data["density"], what=f"vertex densities in {path}",
                  fix="map the mesh again (`tetdose map`, default --solver l2)")
    return mesh
