"""``tetdose dose4d --breathing-trace | --breathing-period-s``: the delivery in time against the
breathing (one fraction, or ``--fractions N --start-phase random``)."""

from __future__ import annotations

import argparse
import json
import time
import tomllib
from pathlib import Path
from typing import Any

import numpy as np

from tetdose._atomic import atomic_write_dir
from tetdose.cli._common import float_in, int_at_least
from tetdose.core.io import write_mesh
from tetdose.dose.dose4d import write_dose4d
from tetdose.dose.fractions import METRICS, FractionCourse, Start, run_fractions
from tetdose.dose.interplay import check_interplay_plan, run_interplay
from tetdose.errors import OptionError
from tetdose.motion.phases import PhaseSeries
from tetdose.motion.trace import BreathingTrace, regular_cycle
from tetdose.plan.delivery import Timeline, delivery_timeline, rt_plan_dose_rates


def add_args(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("interplay: the delivery in time against the breathing")
    g.add_argument("--breathing-trace", type=Path, metavar="CSV",
                   help="breathing trace (columns time_s and phase_percent, or time_s and "
                        "amplitude_mm with --phase-amplitudes-mm): each phase transports only "
                        "the control-point MU delivered while the patient is in it")
    g.add_argument("--phase-amplitudes-mm", type=float, nargs="+", metavar="MM",
                   help="with an amplitude trace: each phase's amplitude, in phase order")
    g.add_argument("--breathing-period-s", type=float_in(0.0, low_open=True), metavar="S",
                   help="a regular breathing cycle of this period instead of a trace")
    g.add_argument("--start-phase", default=None, metavar="PERCENT|random",
                   help="cycle percent at beam-on (default 0), or 'random' (seeded by --seed; "
                        "with a trace: a random beam-on time in it)")
    g.add_argument("--fractions", type=int_at_least(1), default=1,
                   help="N fractions with random starts (needs --start-phase random and "
                        "--target), their mean, the time-weighted 4D dose and the static plan")
    g.add_argument("--target", metavar="STRUCTURE",
                   help="with --fractions: the target ([regions] name or label) whose D95, "
                        "D2 and mean dose are reported")
    g.add_argument("--static-phase", type=float, metavar="PERCENT",
                   help="with --fractions: the phase of the static plan (the planning "
                        "geometry; default the first phase)")


def wanted(args: argparse.Namespace) -> bool:
    """True if the options ask for the delivery in time; refuses options that need it."""
    timed = args.breathing_trace is not None or args.breathing_period_s is not None
    extra = [o for o, v in (("--start-phase", args.start_phase), ("--target", args.target),
                            ("--phase-amplitudes-mm", args.phase_amplitudes_mm),
                            ("--fractions", args.fractions != 1 or None),
                            ("--static-phase", args.static_phase)) if v is not None]
    if not timed and extra:
        raise OptionError(f"{extra[0]} belongs to the delivery in time: give --breathing-trace "
                          "trace.csv or --breathing-period-s S")
    if args.breathing_trace is not None and args.breathing_period_s is not None:
        raise OptionError("give either --breathing-trace or --breathing-period-s, not both")
    if args.fractions > 1 and (args.start_phase != "random" or args.target is None):
        raise OptionError("--fractions N draws random starts and reports a target: add "
                          "--start-phase random --target STRUCTURE")
    return timed


def timeline_for(plan: Any, plan_toml: Path) -> Timeline:  # noqa: ANN401
    """The plan's delivery timeline, with the DoseRateSet of its RT Plan (``rtplan =``)."""
    check_interplay_plan(plan)
    rtplan = tomllib.loads(plan_toml.read_text()).get("rtplan")
    rates = rt_plan_dose_rates(plan_toml.parent / str(rtplan)) if rtplan else None
    return delivery_timeline(plan.treatment_beams, rates)


def starts(args: argparse.Namespace, series: PhaseSeries, timeline: Timeline) -> list[Start]:
    """One :class:`Start` per fraction (random ones seeded by ``--seed``)."""
    rng = np.random.default_rng(args.seed)
    if args.breathing_trace is not None:
        trace = BreathingTrace.read(args.breathing_trace)
        if args.start_phase not in (None, "random"):
            raise OptionError("a trace gives the phase at beam-on; --start-phase random draws "
                              "a random beam-on time in it")
        slack = trace.duration_s - timeline.end_s
        if slack < 0.0:
            raise OptionError(f"the trace lasts {trace.duration_s:g} s, the delivery "
                              f"{timeline.end_s:g} s: give a longer trace")
        s, idx = trace.intervals(series.phase_percent, args.phase_amplitudes_mm)
        t0 = trace.times_s[0] + (rng.uniform(0.0, slack, args.fractions)
                                 if args.start_phase == "random" else np.zeros(1))
        rec = {"file": str(args.breathing_trace), "kind": trace.kind}
        return [Start(s, idx, float(t), {**rec, "beam_on_at_s": float(t)}) for t in t0]
    if args.start_phase in (None, "random"):
        pct = rng.uniform(0.0, 100.0, args.fractions) if args.start_phase else np.zeros(1)
    else:
        try:
            pct = np.array([float(args.start_phase)])
        except ValueError:
            raise OptionError(f"--start-phase {args.start_phase!r}: give a cycle percent or "
                              "'random'") from None
    out = []
    for p in pct:
        s, idx = regular_cycle(args.breathing_period_s, float(p), series.phase_percent,
                               timeline.end_s)
        out.append(Start(s, idx, 0.0, {"period_s": args.breathing_period_s,
                                       "start_phase_percent": float(p)}))
    return out


def run(args: argparse.Namespace, series: PhaseSeries, plan: Any, settings: Any,  # noqa: ANN401
        kwargs: dict[str, Any], unit: str) -> int:
    """One fraction (written as ``dose4d`` writes) or a course (module doc); prints."""
    t_start = time.perf_counter()
    timeline = timeline_for(plan, args.plan)
    course = starts(args, series, timeline)
    if args.fractions == 1:
        s = course[0]
        result = run_interplay(series, plan, settings, timeline, s.starts_s, s.phase_index,
                               t0_s=s.t0_s, trace=s.trace, **kwargs)
        write_dose4d(result, args.output)
        mu = ", ".join(f"{m:.1f}" for m in result.delivery["mu_per_phase"])
        print(f"delivery {timeline.end_s:.1f} s (beam on {timeline.beam_on_s:.1f} s), MU per "
              f"phase {mu}: one fraction's dose max {result.accumulated.dose_gy.max():.4g} "
              f"{unit} → {args.output}")
        return 0
    static = 0 if args.static_phase is None else int(
        np.argmin(np.abs(series.phase_percent - args.static_phase)))
    fc = run_fractions(series, plan, settings, timeline, course, args.target, static, **kwargs)
    report = fc.report(args.seed)
    wall = time.perf_counter() - t_start
    _write_course(fc, report, timeline, wall, unit, args.output)
    _print_course(report, timeline, wall, unit, args.output)
    return 0


def _write_course(fc: FractionCourse, report: dict[str, Any], timeline: Timeline, wall: float,
                  unit: str, out: Path) -> None:
    with atomic_write_dir(out) as tmp:
        write_dose4d(fc.time_weighted, tmp / "time_weighted")
        for f, r in enumerate(fc.fractions, start=1):
            write_dose4d(r, tmp / f"fraction_{f:03d}")
        ref = fc.time_weighted.series.reference
        write_mesh(tmp / "course_mean.vtu", ref.with_data(cell_data={"dose": fc.mean_dose()}))
        summary = {"interplay": report, "delivery": timeline.record(),
                   "starts": [r.delivery["trace"] for r in fc.fractions],
                   "mu_per_phase": [r.delivery["mu_per_phase"] for r in fc.fractions],
                   "units": {"dose": unit}, "wall_s": wall}
        (tmp / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")


def _print_course(rep: dict[str, Any], timeline: Timeline, wall: float, unit: str,
                  out: Path) -> None:
    print(f"delivery {timeline.end_s:.1f} s (beam on {timeline.beam_on_s:.1f} s); target "
          f"{rep['target']}, dose in {unit}")
    print("fraction      " + "".join(f"{m:>12}" for m in METRICS))
    for f, p in enumerate(rep["per_fraction"], start=1):
        print(f"{f:>8}      " + "".join(f"{p[m]:12.4g}" for m in METRICS))
    for name, key in (("mean", "fraction_mean"), ("SD", "fraction_sd"),
                      ("course mean", "course_mean"), ("4D (time)", "time_weighted_4d"),
                      (f"static {rep['static_phase_percent']:g} %", "static_plan")):
        print(f"{name:<14}" + "".join(f"{rep[key][m]:12.4g}" for m in METRICS))
    ref = rep["time_weighted_4d"]
    for m in ("D95", "mean"):
        spread = ", ".join(f"n={s['n']}: {100 * s[f'sd_{m}'] / ref[m]:.2f} %"
                           for s in rep["spread_of_n_fraction_mean"])
        print(f"SD of the {m} of an n-fraction course (relative to the 4D {m}): {spread}")
    print(f"Monte Carlo σ of one fraction's target mean dose "
          f"{100 * rep['statistical_rel_sd_mean_dose']:.2f} %")
    print(f"{rep['fractions']} fractions in {wall:.0f} s → {out}")
