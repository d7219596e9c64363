"""``tetdose demo``: the whole study on the built-in thorax phantom, with a report."""

from __future__ import annotations

import argparse
from dataclasses import replace

from tetdose.study import StudyConfig, run_study


def add_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("-o", "--output", default="demo-out", help="output folder (replaced)")
    p.add_argument("--quick", action="store_true", help="small phantom, few histories (<2 min)")
    p.add_argument("--histories", type=float, help="photons per phase and geometry")
    p.add_argument("--phases", type=int, help="breathing phases (default 10)")
    p.add_argument("--seed", type=int, help="phantom and Monte Carlo seed")


def run(args: argparse.Namespace) -> int:
    config = StudyConfig.quick() if args.quick else StudyConfig()
    changes = {k: v for k, v in (("histories", args.histories and int(args.histories)),
                                  ("n_phases", args.phases), ("seed", args.seed)) if v}
    config = replace(config, **changes)
    summary = run_study(config, args.output, log=print, progress=not args.quiet)
    total = sum(summary["seconds"].values())
    print(f"done in {total:.0f} s → {args.output}/report.html, {args.output}/summary.json")
    return 0
