"""``tetdose demo``: the whole study on the built-in thorax phantom, with a report."""

from __future__ import annotations

import argparse
from dataclasses import replace

from tetdose.cli._common import int_at_least
from tetdose.study import StudyConfig, run_study
from tetdose.transport.run.settings import SPLITTING_SCHEMES


def add_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("-o", "--output", default="demo-out", help="output folder (replaced)")
    p.add_argument("--quick", action="store_true", help="small phantom, few histories (<2 min)")
    p.add_argument("--histories", type=float, help="photons per phase and geometry")
    p.add_argument("--phases", type=int, help="breathing phases (default 10)")
    p.add_argument("--seed", type=int, help="phantom and Monte Carlo seed")
    p.add_argument("--photon-splitting", type=int_at_least(1), metavar="N",
                   help="dose transport: copies per source photon (as `tetdose dose`; the "
                   "demo's default 64 with --splitting-scheme repeat; 1 = analog)")
    p.add_argument("--splitting-scheme", choices=SPLITTING_SCHEMES,
                   help="what splitting does (as `tetdose dose`; the demo's default repeat = "
                   "XVMC's splitting along the ray)")
    p.add_argument("--secondary-photon-splitting", type=int_at_least(1), metavar="N2",
                   help="copies of every later photon of weight 1 (as `tetdose dose`; the "
                   "demo's default 32)")
    p.add_argument("--size-mm", type=_sizes, metavar="NAME=H,…",
                   help="target edge [mm] of meshed structures, e.g. 'tumour=14' (as `tetdose "
                   "mesh --size-mm`, by name): larger tets trade resolution for per-tet "
                   "precision (bench/demo_precision.py)")
    p.add_argument("--quasi-random", action=argparse.BooleanOptionalAction, default=None,
                   help="source photons from scrambled Sobol points (as `tetdose dose`; on by "
                   "default in the demo)")


def _sizes(text: str) -> tuple[tuple[str, float], ...]:
    """'tumour=14,lung=10' → (("tumour", 14.0), ("lung", 10.0))."""
    try:
        return tuple((name.strip(), float(h)) for name, h in
                     (item.split("=") for item in text.split(",")))
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"cannot read {text!r}; write tumour=14 or "
                                         "tumour=14,lung=10") from exc


def run(args: argparse.Namespace) -> int:
    config = StudyConfig.quick() if args.quick else StudyConfig()
    changes = {k: v for k, v in (("histories", args.histories and int(args.histories)),
                                  ("n_phases", args.phases), ("seed", args.seed),
                                  ("photon_splitting", args.photon_splitting),
                                  ("splitting_scheme", args.splitting_scheme),
                                  ("secondary_photon_splitting",
                                   args.secondary_photon_splitting)) if v}
    if args.size_mm:
        changes["mesh_size_mm"] = args.size_mm
    if args.quasi_random is not None:
        changes["quasi_random"] = args.quasi_random
    if ((args.photon_splitting and not args.secondary_photon_splitting)
            or args.splitting_scheme not in (None, "repeat")):
        changes["secondary_photon_splitting"] = None  # as `tetdose dose`: N for every photon
    config = replace(config, **changes)
    summary = run_study(config, args.output, log=print, progress=not args.quiet)
    total = sum(summary["seconds"].values())
    print(f"done in {total:.0f} s → {args.output}/report.html, {args.output}/summary.json")
    return 0
