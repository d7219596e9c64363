"""Command-line interface: ``tetdose COMMAND …`` — density mapping, motion and dose on tet meshes.

Each subcommand lives in its own module with ``add_args(parser)`` and ``run(args) -> int``.
This is the only layer that prints or exits. Every expected failure — a
:class:`~tetdose.errors.TetdoseError`, a bad option, a missing or unwritable file, a full disk —
becomes one line ``tetdose COMMAND: error: …`` on stderr and exit code 2 (a traceback only with
``--debug``); warnings print as one line ``tetdose COMMAND: warning: …``. While a command runs,
every path it is given that exists is declared an input: no atomic write may replace it
(see :func:`tetdose._atomic.output_policy`).
"""

from __future__ import annotations

import argparse
import errno
import importlib
import os
import sys
import traceback
import warnings
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import NoReturn

from tetdose._atomic import output_policy
from tetdose._version import __version__
from tetdose.errors import TetdoseError

#: subcommand → (module, one-line help). Modules are imported only when their command runs.
COMMANDS = {
    "map": ("tetdose.cli._map", "map CT density onto a tetrahedral mesh (vertex densities)"),
    "voxelize": ("tetdose.cli._voxelize", "virtual CT: mesh density back onto a CT grid"),
    "evaluate": ("tetdose.cli._evaluate", "mapping error metrics, error images and figures"),
    "deform": ("tetdose.cli._motion", "breathing phases with mass-conserving vertex density"),
    "register": ("tetdose.cli._register", "real 4D-CT → one displacement field per phase (SimpleITK)"),
    "4dct": ("tetdose.cli._motion", "4D virtual CT: every phase voxelized on a reference CT"),
    "dose": ("tetdose.cli._dose", "Monte Carlo photon dose per tetrahedron or per voxel"),
    "compare": ("tetdose.cli._compare", "mesh vs voxel dose: gamma, DVH, profiles, HTML report"),
    "export-dose": ("tetdose.cli._compare", "dose (mesh or image) → DICOM RT Dose on a CT grid"),
    "dose4d": ("tetdose.cli._dose4d", "dose on every breathing phase, accumulated on the mesh"),
    "demo": ("tetdose.cli._demo", "the whole study on the built-in thorax phantom, with a report"),
    "phantom": ("tetdose.cli._phantom", "write a seeded phantom: CT, labels and tet mesh"),
    "mesh": ("tetdose.cli._mesh", "one conforming tetrahedral mesh of labels (MMG; tetdose[meshing])"),
    "export-phases": ("tetdose.cli._export_phases",
                      "phases as TetGen/ICRP-145 or Abaqus meshes for Geant4, PHITS, MCNP6"),
    "import-dose": ("tetdose.cli._import_dose",
                    "other codes' phase doses onto the mesh, accumulated over the phases"),
}


#: Commands whose -o is a folder replaced as a whole: they all take --overwrite (a command's
#: module may add it itself through cli._common.add_output_args).
FOLDER_OUTPUTS = ("deform", "register", "4dct", "compare", "dose4d", "demo", "phantom",
                  "export-phases", "import-dose")

#: Commands that read a CT: they take --resample-tilted (see tetdose.core.io.tilted_policy).
CT_READERS = ("map", "voxelize", "evaluate", "deform", "register", "4dct", "dose", "export-dose",
              "dose4d", "mesh")

DESCRIPTION = ("CT density on deformable tetrahedral meshes: mass-conserving mapping, breathing "
               "phases, virtual 4D-CT and Monte Carlo photon dose.")


class _Parser(argparse.ArgumentParser):
    """An argument parser whose errors are one line naming the fix, like every other error."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see `{self.prog} --help`)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="tetdose", description=DESCRIPTION)
    parser.add_argument("--version", action="version", version=f"tetdose {__version__}")
    parser.add_argument("--debug", action="store_true",
                        help="show the full traceback of an error (for bug reports)")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (module, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
        p.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                       help="show the full traceback of an error (for bug reports)")
        p.set_defaults(_module=module)
        importlib.import_module(module).add_args(p)
        if name in CT_READERS:
            p.add_argument("--resample-tilted", action="store_true",
                           help="resample a DICOM CT series with a gantry tilt or sheared grid "
                                "onto an orthogonal grid (linear, -1000 HU outside) instead of "
                                "refusing it")
        if name in FOLDER_OUTPUTS and "--overwrite" not in p._option_string_actions:  # noqa: SLF001
            p.add_argument("--overwrite", action="store_true",
                           help="replace the output folder even if tetdose did not write it")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``tetdose`` with ``argv`` (default: ``sys.argv[1:]``); return the exit code."""
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as exc:  # --help, --version, or a usage error already printed
        return exc.code if isinstance(exc.code, int) else 2
    prefix = f"tetdose {args.command}"
    from tetdose.core.io import tilted_policy

    try:
        with _one_line_warnings(prefix), \
                tilted_policy(bool(getattr(args, "resample_tilted", False))), \
                output_policy(inputs=_input_paths(args), force=bool(getattr(args, "overwrite",
                                                                            False))):
            return int(importlib.import_module(args._module).run(args))
    except TetdoseError as exc:
        return _fail(prefix, str(exc), args.debug)
    except OSError as exc:
        message = _os_message(exc)
        if message is None:
            raise
        return _fail(prefix, message, args.debug)
    except KeyboardInterrupt:
        print(f"{prefix}: interrupted; no partial output was kept", file=sys.stderr)
        return 130


def _fail(prefix: str, message: str, debug: bool) -> int:
    if debug:
        traceback.print_exc()
    line = " ".join(message.split())  # one line, whatever the message held
    print(f"{prefix}: error: {line}", file=sys.stderr)
    return 2


def _os_message(exc: OSError) -> str | None:
    """An expected OS error in CLI words, or None for one that is a bug."""
    name = exc.filename if exc.filename is not None else "a file"
    if isinstance(exc, FileNotFoundError):
        return f"{name} does not exist; check the path"
    if isinstance(exc, PermissionError) or exc.errno in (errno.EACCES, errno.EPERM):
        return f"permission denied on {name}; choose a path you can read or write"
    if isinstance(exc, FileExistsError | NotADirectoryError):
        return f"{name} is an existing file where a folder is needed; choose another path"
    if isinstance(exc, IsADirectoryError):
        return f"{name} is a folder where a file is needed; give a file path"
    if exc.errno in (errno.ENOSPC, errno.EDQUOT):
        return f"no space left on the device writing {name}; free some space or use another disk"
    if exc.errno == errno.EROFS:
        return f"{name} is on a read-only file system; write somewhere else"
    return None


def _input_paths(args: argparse.Namespace) -> list[Path]:
    """Every existing path among the arguments except ``--output``."""

    def values() -> Iterator[object]:
        for key, value in vars(args).items():
            if key in ("output", "_module", "command"):
                continue
            yield from value if isinstance(value, list | tuple) else (value,)

    return [Path(v) for v in values()
            if isinstance(v, str | os.PathLike) and str(v) and os.path.exists(v)]


@contextmanager
def _one_line_warnings(prefix: str) -> Iterator[None]:
    """Format warnings as ``PREFIX: warning: MESSAGE`` (no source path) during the block.

    Only the format changes, so callers recording warnings (``pytest.warns``) still see them.
    """
    saved = warnings.formatwarning

    def one_line(message, category, filename, lineno, line=None):  # noqa: ANN001, ANN202, ARG001
        return f"{prefix}: warning: {' '.join(str(message).split())}\n"

    warnings.formatwarning = one_line
    try:
        yield
    finally:
        warnings.formatwarning = saved
