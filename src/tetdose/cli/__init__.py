"""Command-line interface: ``tetdose COMMAND …`` — density mapping, motion and dose on tet meshes.

Each subcommand lives in its own module with ``add_args(parser)`` and ``run(args) -> int``.
This is the only layer that prints or exits. Every expected failure — a
:class:`~tetdose.errors.TetdoseError`, a bad option, a missing or unwritable file, a full disk —
becomes one line ``tetdose COMMAND: error: …`` on stderr and exit code 2 (a traceback only with
``--debug``); warnings print as one line ``tetdose COMMAND: warning: …``. While a command runs,
every path it is given that exists is declared an input: no atomic write may replace it or write
inside it (see :func:`tetdose._atomic.output_policy`).

Before any work, every command (see :func:`main`): checks its outputs (not an input, not inside
an input folder, a writable place); checks that its DICOM inputs belong to one patient and one
frame of reference (:mod:`tetdose.dicom.identity`; ``--allow-frame-mismatch`` warns instead and
records it in every JSON written). While it runs: meshes are read in ``--mesh-unit`` and checked
against the images read (:func:`tetdose.core.io.mesh_unit_policy`); all outputs of the command
are one atomic set (:func:`tetdose._atomic.atomic_outputs`); Ctrl-C (exit 130) and SIGTERM (exit
143) end it with the line ``tetdose COMMAND: interrupted; no partial output was kept``, and an
error leaves no folder it created.
"""

from __future__ import annotations

import argparse
import errno
import importlib
import os
import signal
import sys
import threading
import traceback
import warnings
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import NoReturn

from tetdose._atomic import atomic_outputs, output_policy
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

#: Commands without input files; every other one checks its DICOM inputs (one patient, one
#: frame) and takes --allow-frame-mismatch.
NO_INPUTS = ("demo", "phantom")

#: Commands that read a mesh beside an image: they take --mesh-unit.
MESH_READERS = ("map", "voxelize", "evaluate", "deform", "4dct", "dose", "dose4d", "compare",
                "export-dose")

#: Exit codes of an interrupted command: Ctrl-C (SIGINT) and SIGTERM (128 + signal number).
EXIT_SIGINT, EXIT_SIGTERM = 130, 143


class Terminated(BaseException):
    """SIGTERM arrived: unwinds like Ctrl-C (temporaries removed), exit code 143."""


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
        if name not in NO_INPUTS:
            p.add_argument("--allow-frame-mismatch", action="store_true",
                           help="combine DICOM inputs whose PatientID, FrameOfReferenceUID (or, "
                                "for 4D-CT phases, StudyInstanceUID) differ, with a warning "
                                "recorded in every JSON output, instead of refusing them")
        if name in MESH_READERS:
            p.add_argument("--mesh-unit", choices=("mm", "cm", "m"), default=None,
                           help="unit of the mesh coordinates (default: mm, and a mesh whose "
                                "size or placement does not fit the image is refused with its "
                                "likely unit)")
        if name in FOLDER_OUTPUTS and "--overwrite" not in p._option_string_actions:  # noqa: SLF001
            p.add_argument("--overwrite", action="store_true",
                           help="replace the output folder even if tetdose did not write it")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``tetdose`` with ``argv`` (default: ``sys.argv[1:]``); return the exit code.

    Ctrl-C and SIGTERM give 130 and 143 from the first line on (while the command modules are
    imported for the parser too)."""
    with _sigterm_raises():
        try:
            args = build_parser().parse_args(argv)
        except SystemExit as exc:  # --help, --version, or a usage error already printed
            return exc.code if isinstance(exc.code, int) else 2
        except (KeyboardInterrupt, Terminated) as exc:
            print("tetdose: interrupted; no partial output was kept", file=sys.stderr)
            return EXIT_SIGTERM if isinstance(exc, Terminated) else EXIT_SIGINT
        return _run(args)


def _run(args: argparse.Namespace) -> int:
    prefix = f"tetdose {args.command}"
    from tetdose.core.io import mesh_unit_policy, tilted_policy
    from tetdose.dicom.identity import check_inputs, frame_policy

    created = _missing_folders(getattr(args, "output", None))
    code = 2
    try:
        with _one_line_warnings(prefix), \
                tilted_policy(bool(getattr(args, "resample_tilted", False))), \
                output_policy(inputs=_input_paths(args), force=bool(getattr(args, "overwrite",
                                                                            False))), \
                frame_policy(bool(getattr(args, "allow_frame_mismatch", False))), \
                mesh_unit_policy(getattr(args, "mesh_unit", None)):
            from tetdose.cli._common import check_outputs_first

            module = importlib.import_module(args._module)
            check_outputs_first(args, module)
            check_inputs(_input_paths(args))
            with atomic_outputs():
                code = int(module.run(args))
            return code
    except TetdoseError as exc:
        return _fail(prefix, str(exc), args.debug)
    except OSError as exc:
        message = _os_message(exc)
        if message is None:
            raise
        return _fail(prefix, message, args.debug)
    except KeyboardInterrupt:
        print(f"{prefix}: interrupted; no partial output was kept", file=sys.stderr)
        return EXIT_SIGINT
    except Terminated:
        print(f"{prefix}: interrupted; no partial output was kept", file=sys.stderr)
        return EXIT_SIGTERM
    finally:
        if code != 0:
            _remove_empty(created)


@contextmanager
def _sigterm_raises() -> Iterator[None]:
    """SIGTERM raises :class:`Terminated` in the main thread during the block (so atomic writes
    clean up and the command exits 143), then the previous handler is back."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):  # noqa: ANN001, ANN202, ARG001
        raise Terminated

    previous = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _missing_folders(output: object) -> list[Path]:
    """The folders of ``output`` (itself included) that do not exist yet, deepest first."""
    if not isinstance(output, str | os.PathLike) or not str(output):
        return []
    missing = []
    p = Path(os.path.abspath(output))
    while not p.exists() and p != p.parent:
        missing.append(p)
        p = p.parent
    return missing


def _remove_empty(folders: Sequence[Path]) -> None:
    """Remove the folders (deepest first) that a failed command created and left empty."""
    for folder in folders:
        try:
            if folder.is_dir() and not any(folder.iterdir()):
                folder.rmdir()
        except OSError:
            return


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
