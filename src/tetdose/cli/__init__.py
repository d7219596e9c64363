"""Command-line interface: ``tetdose SUBCOMMAND …`` (meshio ``_cli`` pattern).

Each subcommand lives in its own module with ``add_args(parser)`` and ``run(args) -> int``.
This is the only layer that prints or exits: a :class:`~tetdose.errors.TetdoseError` becomes a
one-line message on stderr and exit code 2.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from tetdose import __version__
from tetdose.errors import TetdoseError

#: subcommand → (module, one-line help). Modules are imported only when their command runs.
COMMANDS = {
    "map": ("tetdose.cli._map", "map CT density onto a tetrahedral mesh (vertex densities)"),
    "voxelize": ("tetdose.cli._voxelize", "virtual CT: mesh density back onto a CT grid"),
    "evaluate": ("tetdose.cli._evaluate", "mapping error metrics, error images and figures"),
    "deform": ("tetdose.cli._motion", "breathing phases with mass-conserving vertex density"),
    "4dct": ("tetdose.cli._motion", "4D virtual CT: every phase voxelized on a reference CT"),
    "dose": ("tetdose.cli._dose", "Monte Carlo photon dose per tetrahedron or per voxel"),
    "compare": ("tetdose.cli._compare", "mesh vs voxel dose: gamma, DVH, profiles, HTML report"),
    "export-dose": ("tetdose.cli._compare", "dose (mesh or image) → DICOM RT Dose on a CT grid"),
    "dose4d": ("tetdose.cli._dose4d", "dose on every breathing phase, accumulated on the mesh"),
    "demo": ("tetdose.cli._demo", "the whole study on the built-in thorax phantom, with a report"),
    "phantom": ("tetdose.cli._phantom", "write a seeded phantom: CT, labels and tet mesh"),
    "mesh": ("tetdose.cli._mesh", "one conforming tetrahedral mesh of labels (MMG; tetdose[meshing])"),
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="tetdose", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"tetdose {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (module, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
        p.set_defaults(_module=module)
        importlib.import_module(module).add_args(p)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``tetdose`` with ``argv`` (default: ``sys.argv[1:]``); return the exit code."""
    args = build_parser().parse_args(argv)
    try:
        return int(importlib.import_module(args._module).run(args))
    except TetdoseError as exc:
        print(f"tetdose {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"tetdose {args.command}: interrupted; no partial output was kept", file=sys.stderr)
        return 130
