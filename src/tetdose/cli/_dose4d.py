"""``tetdose dose4d``: dose on every breathing phase, accumulated on the mesh (and on voxels)."""

from __future__ import annotations

import argparse
from pathlib import Path

from tetdose.cli._common import add_calibration_arg, calibration_from
from tetdose.cli._dose import add_dask_arg, dask_context
from tetdose.dose4d import run_dose4d, write_dose4d
from tetdose.io import read_image
from tetdose.motion.phases import PhaseSeries
from tetdose.prescription import PER_PHOTON_UNIT
from tetdose.transport import Plan, TransportSettings
from tetdose.transport.model import ESTIMATORS


def add_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--phases", type=Path, required=True,
                   help="folder written by `tetdose deform` (phase VTUs + phases.pvd)")
    p.add_argument("--plan", type=Path, required=True, help="plan.toml (beams, materials)")
    p.add_argument("--histories", type=float, default=1e6, help="source photons per phase")
    p.add_argument("--seed", type=int, default=1, help="master random seed")
    p.add_argument("--batches", type=int, default=10, help="independent batches (for σ)")
    p.add_argument("--estimator", choices=ESTIMATORS, default="track_length",
                   help="dose tally (default: track_length)")
    p.add_argument("--like", type=Path,
                   help="reference CT: also compute voxel doses on the virtual 4D-CT and "
                        "accumulate them by direct dose mapping and energy/mass transfer")
    p.add_argument("-o", "--output", type=Path, required=True, help="output folder")
    add_calibration_arg(p)
    add_dask_arg(p)
    p.add_argument("--batches-per-task", type=int, default=1,
                   help="with --dask: batches per dask task (default 1)")


def run(args: argparse.Namespace) -> int:
    series = PhaseSeries.read(None, args.phases)
    plan = Plan.from_toml(args.plan)
    settings = TransportSettings(n_histories=int(args.histories), n_batches=args.batches,
                                 seed=args.seed, estimator=args.estimator)
    ct = read_image(args.like) if args.like else None
    with dask_context(args.dask) as client:
        result = run_dose4d(series, plan, settings, ct_hu=ct, calibration=calibration_from(args),
                            progress=not args.quiet, client=client,
                            batches_per_task=args.batches_per_task)
    write_dose4d(result, args.output)
    unit = result.summary()["units"]["dose"]
    if unit == PER_PHOTON_UNIT and plan.particles != 1.0:
        unit = f"Gy per {plan.particles:g} source photons"
    print(f"{series.n_phases} phases × {settings.n_histories} histories: accumulated dose max "
          f"{result.accumulated.dose_gy.max():.4g} {unit} → {args.output}")
    return 0
