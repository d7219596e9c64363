"""``tetdose dose``: photon dose on a mapped mesh (per tetrahedron) or a CT (per voxel).

Writes the dose (cell_data ``dose``/``dose_std`` in Gy for a mesh; ``dose`` and ``*_std`` images
for a CT) and the JSON run record beside it (``dose.json`` for ``dose.vtu``).
"""

from __future__ import annotations

import argparse
from contextlib import nullcontext
from pathlib import Path
from typing import Any

import numpy as np

from tetdose.errors import PlanError


def add_args(parser: argparse.ArgumentParser) -> None:
    src = parser.add_mutually_exclusive_group(required=True)
    src.add_argument("--mesh", type=Path, help="mapped mesh (VTU with point_data density g/cm³)")
    src.add_argument("--ct", type=Path, help="CT image or DICOM folder (HU)")
    parser.add_argument("--plan", type=Path,
                        help="plan.toml (beams, materials, regions, prescription)")
    parser.add_argument("--rtplan", type=Path,
                        help="DICOM RT Plan: its photon beams are added to --plan's (or used "
                             "alone)")
    parser.add_argument("--histories", type=float, default=1e6, help="source photons (e.g. 1e7)")
    parser.add_argument("--seed", type=int, default=1, help="master random seed")
    parser.add_argument("--batches", type=int, default=10, help="independent batches (for σ)")
    parser.add_argument("--estimator", choices=("track_length", "analog"),
                        default="track_length", help="dose tally (default: track_length)")
    parser.add_argument("--cutoff-mev", type=float, default=0.01,
                        help="photon energy cut-off, deposited locally [MeV]")
    parser.add_argument("--calibration", type=Path,
                        help="HU→density CSV for --ct (default: Schneider 2000)")
    parser.add_argument("--labels", type=Path, help="label image for --ct (region → [materials])")
    parser.add_argument("-o", "--output", type=Path, required=True,
                        help="dose.vtu (with --mesh) or dose.nrrd / .mha / .nii.gz (with --ct)")
    add_dask_arg(parser)


def add_dask_arg(parser: argparse.ArgumentParser) -> None:
    """``--dask SCHEDULER|local:N`` (shared with ``tetdose dose4d``)."""
    parser.add_argument("--dask", metavar="SCHEDULER|local:N",
                        help="spread the batches over a dask.distributed cluster: a scheduler "
                             "address (tcp://host:8786) or local:N for N worker processes here; "
                             "same dose, bit for bit (needs tetdose[dask])")


def dask_context(spec: str | None) -> Any:  # noqa: ANN401 - context manager
    """A context yielding a dask client for ``--dask``, or None without it."""
    if spec is None:
        return nullcontext(None)
    from tetdose.transport.distributed import dask_client

    return dask_client(spec)


def _simulate(client: Any, geometry: Any, plan: Any, settings: Any, **kw: Any) -> Any:  # noqa: ANN401
    from tetdose.transport import simulate
    from tetdose.transport.distributed import simulate_distributed

    if client is None:
        return simulate(geometry, plan, settings, **kw)
    return simulate_distributed(client, geometry, plan, settings, **kw)


def load_plan(plan_toml: Path | None, rtplan: Path | None) -> Any:  # noqa: ANN401
    """``--plan`` and/or ``--rtplan``: the RT Plan's beams join the plan.toml's."""
    from tetdose.dicom.rt_plan import read_rt_plan
    from tetdose.transport import Plan

    if plan_toml is None and rtplan is None:
        raise PlanError("give --plan plan.toml, --rtplan plan.dcm, or both")
    if plan_toml is None:
        return read_rt_plan(rtplan)
    return Plan.from_toml(plan_toml, rtplan=rtplan)


def record_path(output: Path) -> Path:
    """``dose.json`` beside ``dose.vtu`` (all suffixes replaced, so dose.nii.gz → dose.json)."""
    return output.with_name(output.name.split(".")[0] + ".json")


def _std_path(output: Path) -> Path:
    stem, _, rest = output.name.partition(".")
    return output.with_name(f"{stem}_std.{rest}")


def run(args: argparse.Namespace) -> int:
    from tetdose.calibration import HUCalibration
    from tetdose.io import read_image, read_mesh, write_image, write_mesh
    from tetdose.prescription import prescribe_result
    from tetdose.transport import TransportSettings

    if args.histories != int(args.histories) or args.histories < 1:
        raise PlanError(f"--histories must be a positive whole number, got {args.histories:g}")
    plan = load_plan(args.plan, args.rtplan)
    settings = TransportSettings(int(args.histories), args.batches, args.seed,
                                 args.cutoff_mev, args.estimator)
    progress = False if args.quiet else None
    extra: dict[str, object] = {"plan": str(args.plan), "rtplan": str(args.rtplan),
                                "dask": args.dask}
    if args.mesh is not None:
        if args.output.suffix.lower() not in (".vtu", ".vtk", ".xdmf", ".msh"):
            raise PlanError(f"with --mesh the output must be a mesh file (.vtu), got {args.output}")
        mesh = read_mesh(args.mesh)
        plan = plan.resolved(mesh)
        with dask_context(args.dask) as client:
            result = _simulate(client, mesh, plan, settings, progress=progress)
        result = prescribe_result(result, plan, mesh)
        write_mesh(args.output, result.to_mesh(mesh))
        extra.update(mesh=str(args.mesh), outputs=[str(args.output)])
    else:
        ct = read_image(args.ct)
        cal = (HUCalibration.from_csv(args.calibration) if args.calibration
               else HUCalibration.schneider2000())
        density = ct.with_array(cal.density(ct.array).astype(np.float64))
        labels = read_image(args.labels) if args.labels else None
        plan = plan.resolved(density, labels)
        with dask_context(args.dask) as client:
            result = _simulate(client, density, plan, settings, labels=labels, progress=progress)
        result = prescribe_result(result, plan, density, labels)
        dose, dose_std = result.to_images()
        write_image(args.output, dose.with_array(dose.array.astype(np.float32)))
        write_image(_std_path(args.output), dose_std.with_array(dose_std.array.astype(np.float32)))
        extra.update(ct=str(args.ct), calibration=cal.name,
                     outputs=[str(args.output), str(_std_path(args.output))])
    result.extra.update(extra)
    path = result.save_json(record_path(args.output))
    if not args.quiet:
        led = result.ledger
        unit = result.extra.get("units", {}).get("dose", "Gy")
        print(f"dose: {result.n_histories} histories in {result.wall_s:.1f} s; max "
              f"{result.dose_gy.max():.4g} {unit}; deposited {led['deposited_mev']:.4g} MeV and "
              f"escaped {led['escaped_mev']:.4g} MeV per particle → {args.output}, {path}")
    return 0
