"""``tetdose dose4d``: dose on every breathing phase, accumulated on the mesh (and on voxels)."""

from __future__ import annotations

import argparse
from pathlib import Path

from tetdose.cli import _interplay
from tetdose.cli._common import add_calibration_arg, calibration_from, check_output, int_at_least
from tetdose.cli._dose import (
    add_ct_materials_arg,
    add_dask_arg,
    add_engine_args,
    add_run_args,
    dask_context,
    ompmc_options,
    run_settings,
    target_line,
)
from tetdose.core.io import read_ct
from tetdose.core.phase_names import order_by_names
from tetdose.dose.dose4d import run_dose4d, write_dose4d
from tetdose.errors import OptionError
from tetdose.motion.ct4d_read import SERIES_FIX, find_phase, read_4dct
from tetdose.motion.dvf import read_dvf
from tetdose.motion.phases import PhaseSeries
from tetdose.plan.prescription import PER_PHOTON_UNIT
from tetdose.transport import Plan


def add_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--phases", type=Path, required=True,
                   help="folder written by `tetdose deform` (phase VTUs + phases.pvd)")
    p.add_argument("--plan", type=Path, required=True, help="plan.toml (beams, materials)")
    add_run_args(p, " per phase")
    p.add_argument("--like", type=Path,
                   help="reference CT: every phase's mesh runs inside the phase's body (the "
                        "hybrid world), and the voxel-only dose on the same body is accumulated "
                        "by direct dose mapping and energy/mass transfer")
    p.add_argument("--ct4d", nargs="+", type=Path, metavar="CT4D",
                   help="a real 4D-CT (folder of phase series, or phase image files): each "
                        "phase's CT, matched to the mesh phase by its percentage, is that "
                        "phase's body (on one grid)")
    p.add_argument("--dvf", nargs="+", type=Path, metavar="IMAGE",
                   help="with --like: the phases' displacement fields (as for `tetdose deform "
                        "--dvf`): the reference CT warped by each is the body outside the mesh")
    p.add_argument("-o", "--output", type=Path, required=True, help="output folder")
    add_calibration_arg(p)
    add_ct_materials_arg(p, "phase bodies' voxels (--like, --ct4d) outside the mesh")
    add_dask_arg(p)
    p.add_argument("--batches-per-task", type=int_at_least(1), default=1,
                   help="with --dask: batches per dask task (default 1)")
    add_engine_args(p)
    _interplay.add_args(p)


def run(args: argparse.Namespace) -> int:
    check_output(args, folder=True)
    timed = _interplay.wanted(args)
    series = PhaseSeries.read(None, args.phases)
    plan = Plan.from_toml(args.plan)
    settings = run_settings(args)
    ct = read_ct(args.like) if args.like else None
    if args.dvf and ct is None:
        raise OptionError("--dvf warps the reference CT of --like; give --like too")
    if args.dvf and args.ct4d:
        raise OptionError("give either --ct4d (the real phase CTs are the bodies) or --dvf "
                          "(the warped reference CT is), not both")
    dvfs = ([read_dvf(f) for f in order_by_names(args.dvf, series.phase_percent, "--dvf")]
            if args.dvf else None)
    phase_ct = None
    if args.ct4d:
        ct4d = read_4dct(args.ct4d[0] if len(args.ct4d) == 1 else args.ct4d)
        phase_ct = [ct4d[find_phase(ct4d, float(pct), fix=SERIES_FIX,
                                    what=f" for the phase mesh at {pct:g} % of {args.phases}")
                         ].image for pct in series.phase_percent]
    engine = None
    if args.engine == "ompmc":
        from tetdose.coupling.ompmc import phase_engine

        if args.dask is not None:
            raise OptionError("--dask spreads tetdose's engine; ompmc runs here on OpenMP "
                              "threads: drop --dask")
        if ct is None and phase_ct is None:
            raise OptionError("--engine ompmc runs on each phase's CT: give --like (the "
                              "reference CT, virtual phase CTs) or --ct4d (the real ones)")
        engine = phase_engine(ompmc_options(args), progress=False if args.quiet else None)
    with dask_context(args.dask) as client:
        kwargs = {"ct_hu": ct, "calibration": calibration_from(args), "phase_ct": phase_ct,
                  "dvfs": dvfs, "progress": not args.quiet, "client": client,
                  "batches_per_task": args.batches_per_task, "voxel_engine": engine,
                  "ct_materials": args.ct_materials}
        if timed:
            return _interplay.run(args, series, plan, settings, kwargs, _unit(plan))
        result = run_dose4d(series, plan, settings, **kwargs)
    write_dose4d(result, args.output)
    unit = result.summary()["units"]["dose"]
    if unit == PER_PHOTON_UNIT and plan.particles != 1.0:
        unit = f"Gy per {plan.particles:g} source photons"
    print(f"{series.n_phases} phases × {settings.n_histories} histories: accumulated dose max "
          f"{result.accumulated.dose_gy.max():.4g} {unit} → {args.output}")
    targets = [r.extra["target"] for r in result.results if "target" in r.extra]
    if targets:
        print(target_line(targets).replace("run(s)", "phases"))
    return 0


def _unit(plan: Plan) -> str:
    """The dose unit of an interplay run's outputs (no prescription there)."""
    if plan.calibration is not None:
        from tetdose.plan.mu_calibration import MU_UNIT

        return MU_UNIT
    return PER_PHOTON_UNIT if plan.particles == 1.0 else \
        f"Gy per {plan.particles:g} source photons"
