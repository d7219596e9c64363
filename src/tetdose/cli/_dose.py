"""``tetdose dose``: photon dose on a mapped mesh, a CT, or the mesh inside the CT (hybrid).

``--mesh`` alone: the mesh in vacuum, dose per tetrahedron (``-o dose.vtu``). ``--ct`` alone: dose
per voxel (``-o dose.nrrd``). Both: the hybrid world — the mesh is the truth inside it, the CT's
voxels outside — writing ``dose.vtu`` (mesh part), ``dose.nrrd`` + ``dose_std.nrrd`` beside it
(the combined dose on the CT grid: mesh energy put on the voxels through the exact overlaps) and
``dose_voxels.nrrd`` (the voxel part alone; voxels inside the mesh 0). Always the JSON run record
beside the output (``dose.json`` for ``dose.vtu``).
"""

from __future__ import annotations

import argparse
import warnings
from contextlib import nullcontext
from pathlib import Path
from typing import Any

import numpy as np

from tetdose.cli._common import (
    add_calibration_arg,
    calibration_from,
    count,
    float_in,
    int_at_least,
    read_mapped_mesh,
)
from tetdose.errors import OptionError, PlanError
from tetdose.transport.run.settings import (
    ELECTRON_CUTOFF_MEV,
    ESTIMATORS,
    MAX_ENERGY_LOSS_FRACTION,
    PHOTON_SPLITTING,
    PHOTON_TRACKING,
    PHYSICS,
    RANGE_REJECTION_MEV,
    SPLITTING_SCHEMES,
    TARGET_STATISTICS,
)

MESH_SUFFIXES = (".vtu", ".vtk", ".xdmf", ".msh")


def add_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--mesh", type=Path,
                        help="mapped mesh (VTU with point_data density g/cm³); with --ct: the "
                             "part of the patient that is meshed")
    parser.add_argument("--ct", type=Path,
                        help="CT image or DICOM folder (HU); with --mesh: the rest of the body")
    parser.add_argument("--plan", type=Path,
                        help="plan.toml (beams, materials, regions, prescription)")
    parser.add_argument("--rtplan", type=Path,
                        help="DICOM RT Plan: its photon beams are added to --plan's (or used "
                             "alone)")
    parser.add_argument("--fraction-group", type=int_at_least(1), metavar="N",
                        help="the --rtplan fraction group to compute (FractionGroupNumber); "
                             "needed when the RT Plan has several")
    add_run_args(parser)
    parser.add_argument("--cutoff-mev", type=float_in(0.0, 20.0, low_open=True), default=0.01,
                        help="photon energy cut-off, deposited locally [MeV]")
    add_calibration_arg(parser)
    parser.add_argument("--labels", type=Path, help="label image for --ct (region → [materials])")
    add_ct_materials_arg(parser, "CT voxels no [materials] region claims")
    parser.add_argument("-o", "--output", type=Path, required=True,
                        help="dose.vtu (with --mesh, also with --ct) or dose.nrrd / .mha / "
                             ".nii.gz (--ct alone)")
    parser.add_argument("--vertex-dose", action="store_true",
                        help="with --mesh: also the dose on the vertices (mass-weighted L2 "
                        "projection onto the linear basis), point_data dose_vertex and "
                        "dose_vertex_std [Gy]")
    add_dask_arg(parser)
    add_engine_args(parser)


def add_ct_materials_arg(parser: argparse.ArgumentParser, what: str) -> None:
    parser.add_argument("--ct-materials", choices=("schneider", "density-classes"),
                        default="schneider",
                        help=f"composition of the {what}: Schneider et al. 2000's HU bins "
                        "(default; 24 compositions) or the five density classes (air, lung, "
                        "adipose, soft tissue, bone); recorded in the outputs")


#: Transport engines of ``--engine``.
ENGINES = ("tetdose", "ompmc")


def add_engine_args(parser: argparse.ArgumentParser) -> None:
    """``--engine`` and the ompmc options (shared with ``dose4d``)."""
    parser.add_argument("--engine", choices=ENGINES, default="tetdose",
                        help="transport engine: tetdose's own, or ompmc (EGSnrc coupled "
                             "photon-electron physics on the CT's voxels; needs tetdose[ompmc] "
                             "and a CT; a mesh gets the voxel dose by energy)")
    parser.add_argument("--ompmc-pegs", default="521icru", metavar="521icru|700icru|FILE",
                        help="ompmc's PEGS4 media data (521icru: 10 keV electron cut-off)")
    parser.add_argument("--ompmc-split", type=int_at_least(1), default=20,
                        help="ompmc photon splitting factor (1 = none)")


def ompmc_options(args: argparse.Namespace) -> Any:  # noqa: ANN401
    """The :class:`tetdose.coupling.ompmc.OmpmcOptions` of the command line."""
    from tetdose.coupling.ompmc import OmpmcOptions

    cutoff = getattr(args, "electron_cutoff_mev", None)
    return OmpmcOptions(pegs=args.ompmc_pegs, n_split=args.ompmc_split,
                        **({} if cutoff is None else {"electron_cutoff_mev": cutoff}))


def add_run_args(parser: argparse.ArgumentParser, per: str = "") -> None:
    """``--histories``, ``--seed``, ``--batches``, ``--estimator`` (shared with ``dose4d``),
    range-checked at parse time."""
    parser.add_argument("--histories", type=count, default=1e6,
                        help=f"source photons{per} (e.g. 1e7)")
    parser.add_argument("--seed", type=int_at_least(0), default=1, help="master random seed")
    parser.add_argument("--batches", type=int_at_least(2), default=10,
                        help="independent batches (≥ 2, for σ)")
    parser.add_argument("--estimator", choices=ESTIMATORS, default=None,
                        help="dose tally (default: analog with --physics dose, track_length "
                             "with kerma)")
    parser.add_argument("--physics", choices=PHYSICS, default="dose",
                        help="dose: electrons transported, absorbed dose (default); kerma: "
                             "charged particles deposit where they are born (fast)")
    parser.add_argument("--electron-cutoff-mev", type=float_in(0.001, 20.0),
                        default=ELECTRON_CUTOFF_MEV,
                        help=f"electron/positron cut-off and δ-ray threshold, kinetic [MeV] "
                             f"(default {ELECTRON_CUTOFF_MEV})")
    parser.add_argument("--max-energy-loss-fraction", type=float_in(0.01, 0.5),
                        default=MAX_ENERGY_LOSS_FRACTION, metavar="F",
                        help="dose mode: the largest fraction of its energy an electron loses "
                        f"in one step (EGSnrc's ESTEPE; default {MAX_ENERGY_LOSS_FRACTION:g}). "
                        "0.5 is 1.1–1.5× more efficient with --splitting-scheme repeat and passes the Fano "
                        "test and EGSnrc's 2 MeV water/lung slab, but moves a 6 MeV electron "
                        "beam's depth dose by up to 4.6 %% of D_max")
    parser.add_argument("--photon-splitting", type=int_at_least(1), default=PHOTON_SPLITTING,
                        metavar="N", help="dose mode: follow each source photon as N copies of "
                        "weight 1/N, Russian roulette for the electrons they set in motion "
                        f"(unbiased; default {PHOTON_SPLITTING} = none)")
    parser.add_argument("--splitting-scheme", choices=SPLITTING_SCHEMES, default="roulette",
                        help="dose mode, with --photon-splitting N > 1: roulette = Russian "
                        "roulette for the split photons' electrons (EGSnrc, default); follow = "
                        "follow them all with weight 1/N, roulette for the secondary photons "
                        "(XVMC); repeat = XVMC's splitting along the ray: every photon of "
                        "weight 1 split into N copies at evenly spaced depths, one shared "
                        "interaction and one electron track replayed from each copy's site")
    parser.add_argument("--secondary-photon-splitting", type=int_at_least(1), metavar="N2",
                        help="with --splitting-scheme repeat: copies of every photon of weight 1 "
                        "after the source photon (the scattered photon kept, bremsstrahlung), at "
                        "most --photon-splitting (default: as many as the source photon's)")
    parser.add_argument("--range-rejection-mev", type=float_in(0.0, 20.0),
                        default=RANGE_REJECTION_MEV, metavar="MEV",
                        help="dose mode: an electron up to this energy that cannot leave its "
                        "voxel or tet deposits there at once (0 = off; default "
                        f"{RANGE_REJECTION_MEV:g})")
    parser.add_argument("--photon-tracking", choices=PHOTON_TRACKING, default="woodcock",
                        help="dose mode: photons cross the mesh by Woodcock (delta) tracking "
                        "(default) or walk it tet by tet (same dose within statistics)")
    parser.add_argument("--quasi-random", action="store_true",
                        help="source particles' position, energy and beam from scrambled Sobol "
                        "points, one independent scramble per batch (unbiased; less noise)")

    parser.add_argument("--dose-to", choices=("medium", "water"), default="medium",
                        help="report dose to medium (D_m, default) or dose to water (D_w = D_m "
                        "× the water-to-medium stopping-power ratio of each cell's medium, "
                        "Siebers et al. 2000); recorded in every output")
    parser.add_argument("--target-uncertainty", type=relative_uncertainty, metavar="PCT",
                        help="stop once the mean dose in --target-region has this relative "
                             "standard error (e.g. 1%% or 0.01); --histories is then the cap "
                             "(runs here, not with --dask; more --batches stop finer)")
    parser.add_argument("--target-region", metavar="NAME|LABEL",
                        help="structure of --target-uncertainty (default: the prescription's)")
    parser.add_argument("--target-statistic", choices=TARGET_STATISTICS, default="mean",
                        help="what --target-uncertainty bounds: the σ of the structure's mean "
                        "dose (default), or the median σ of its tets/voxels")


def relative_uncertainty(text: str) -> float:
    """``1%`` → 0.01, ``0.01`` → 0.01; refused outside (0, 1)."""
    try:
        value = float(text[:-1]) / 100.0 if text.endswith("%") else float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number or a percentage (e.g. 1%)"
                                         ) from None
    if not 0.0 < value < 1.0:
        raise argparse.ArgumentTypeError(f"{text!r}: give a relative uncertainty between 0 and "
                                         "100 %, e.g. 1%")
    return value


def run_settings(args: argparse.Namespace, **kw: Any) -> Any:  # noqa: ANN401
    """TransportSettings from the shared run options (:func:`add_run_args`) and ``kw``."""
    from tetdose.transport import TransportSettings

    if args.target_uncertainty is not None and getattr(args, "dask", None):
        raise OptionError("--target-uncertainty stops a run here; it does not work with --dask "
                          "(give --histories instead)")
    return TransportSettings(n_histories=int(args.histories), n_batches=args.batches,
                             seed=args.seed, estimator=args.estimator,
                             target_uncertainty=args.target_uncertainty,
                             target_region=args.target_region,
                             target_statistic=args.target_statistic, physics=args.physics,
                             electron_cutoff_mev=args.electron_cutoff_mev,
                             max_energy_loss_fraction=args.max_energy_loss_fraction,
                             photon_splitting=args.photon_splitting,
                             splitting_scheme=args.splitting_scheme,
                             secondary_photon_splitting=args.secondary_photon_splitting,
                             range_rejection_mev=args.range_rejection_mev,
                             photon_tracking=args.photon_tracking, dose_to=args.dose_to,
                             quasi_random=args.quasi_random, **kw)


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
    from tetdose.transport.run.distributed import dask_client

    return dask_client(spec)


def load_plan(plan_toml: Path | None, rtplan: Path | None,
              fraction_group: int | None = None) -> Any:  # noqa: ANN401
    """``--plan`` and/or ``--rtplan`` (its ``--fraction-group``): the RT Plan's beams join the
    plan.toml's."""
    from tetdose.transport import Plan

    if plan_toml is None and rtplan is None:
        raise PlanError("give --plan plan.toml, --rtplan plan.dcm, or both")
    if plan_toml is None:
        return Plan.from_rt_plan(rtplan, fraction_group)
    return Plan.from_toml(plan_toml, rtplan=rtplan, fraction_group=fraction_group)


def record_path(output: Path) -> Path:
    """``dose.json`` beside ``dose.vtu`` (all suffixes replaced, so dose.nii.gz → dose.json)."""
    return output.with_name(output.name.split(".")[0] + ".json")


def output_files(args: argparse.Namespace) -> list[Path]:
    """The files ``run`` writes beside ``-o`` (checked before any work, written as one set with
    it): the images, the JSON record."""
    out = Path(args.output)
    files: list[Path] = []
    if args.ct is not None:
        image = _sibling(out, ext="nrrd") if args.mesh is not None else out
        files += [image, _sibling(image, "_std")]
        if args.mesh is not None:
            files.append(_sibling(out, "_voxels", "nrrd"))
    return list(dict.fromkeys([*files, record_path(out)]))


def _sibling(output: Path, suffix: str = "", ext: str | None = None) -> Path:
    """``dose_std.nrrd`` for ``dose.nrrd`` (suffix "_std"); ``dose.nrrd`` for ``dose.vtu``
    (ext "nrrd")."""
    stem, _, rest = output.name.partition(".")
    return output.with_name(f"{stem}{suffix}.{ext or rest}")


def _write_images(result: Any, output: Path) -> list[str]:  # noqa: ANN401
    """The (combined) dose and its σ as float32 images: ``output`` and ``*_std``."""
    from tetdose.core.io import write_image

    dose, dose_std = result.to_images()
    write_image(output, dose.with_array(dose.array.astype(np.float32)))
    write_image(_sibling(output, "_std"), dose_std.with_array(dose_std.array.astype(np.float32)))
    return [str(output), str(_sibling(output, "_std"))]


def run(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from tetdose.core.icrp145 import is_icrp145, phantom_compositions
    from tetdose.core.io import read_ct, read_labels, write_image, write_mesh
    from tetdose.dose.absolute import absolute_result
    from tetdose.dose.dose_to import mark
    from tetdose.transport import World
    from tetdose.transport.run.distributed import simulate_on

    if args.mesh is None and args.ct is None:
        raise PlanError("give --mesh (a mapped mesh), --ct (a CT), or both (the mesh inside "
                        "the CT)")
    is_mesh_out = args.output.suffix.lower() in MESH_SUFFIXES
    if args.mesh is not None and not is_mesh_out:
        raise PlanError(f"with --mesh the output must be a mesh file (.vtu), got {args.output}")
    if args.mesh is None and is_mesh_out:
        raise PlanError(f"with --ct alone the output must be an image (.nrrd), got {args.output}")
    if args.labels is not None and args.ct is None:
        raise PlanError("--labels labels the CT's voxels; give --ct too")
    plan = load_plan(args.plan, args.rtplan, args.fraction_group)
    settings = run_settings(args, energy_cutoff_mev=args.cutoff_mev)
    progress = False if args.quiet else None
    extra: dict[str, object] = {"plan": str(args.plan), "rtplan": str(args.rtplan),
                                "dask": args.dask}
    mesh = read_mapped_mesh(args.mesh) if args.mesh is not None else None
    if args.mesh is not None and is_icrp145(args.mesh):  # the phantom's own compositions
        ids, comps = phantom_compositions(args.mesh)
        plan = replace(plan, materials={**ids, **plan.materials},
                       compositions={**comps, **plan.compositions})
    density = labels = None
    if args.ct is not None:
        ct = read_ct(args.ct)
        cal = calibration_from(args)
        rho, beyond = cal.density_checked(ct.array, f"the CT {args.ct}")
        density = ct.with_array(rho.astype(np.float64))
        labels = read_labels(args.labels) if args.labels else None
        extra.update(ct=str(args.ct), calibration=cal.name,
                     hu_beyond_calibration=beyond.as_dict())
        if args.ct_materials == "schneider" and labels is None and mesh is None and plan.materials:
            warnings.warn("plan [materials] given but the CT has no region labels (--labels); "
                          "its voxels get Schneider's HU compositions", stacklevel=2)
        plan, labels, extra["ct_materials"] = ct_materials(args.ct_materials, plan, ct, cal,
                                                           labels)
    if args.vertex_dose and (mesh is None or args.engine == "ompmc"):
        raise OptionError("--vertex-dose projects the mesh's dose of tetdose's engine: give "
                          "--mesh (and no --engine ompmc), or drop --vertex-dose")
    if args.engine == "ompmc":
        return _run_ompmc(args, plan, settings, mesh, density, labels, extra, progress)
    world = World(mesh=mesh, density=density, labels=labels)
    plan = plan.resolved(world)
    with dask_context(args.dask) as client:
        result = simulate_on(client, world, plan, settings, progress=progress)
    result = absolute_result(result, plan, world)
    outputs: list[str] = []
    if mesh is not None:
        out_mesh = result.to_mesh(mesh)
        if args.vertex_dose:
            from tetdose.dose.vertex import with_vertex_dose

            out_mesh = with_vertex_dose(out_mesh, result)
        write_mesh(args.output, mark(out_mesh, settings.dose_to))
        outputs.append(str(args.output))
        extra["mesh"] = str(args.mesh)
    if density is not None:
        image_out = _sibling(args.output, ext="nrrd") if mesh is not None else args.output
        outputs += _write_images(result, image_out)
        if mesh is not None:
            part, _ = result.voxel_part().to_images()
            voxels_out = _sibling(args.output, "_voxels", "nrrd")
            write_image(voxels_out, part.with_array(part.array.astype(np.float32)))
            outputs.append(str(voxels_out))
    result = result.with_extra(**extra, world=world.kind, outputs=outputs)
    path = result.save_json(record_path(args.output),
                            None if mesh is None else mesh.volumes_mm3)
    if not args.quiet:
        print(summary_line(result, world.kind, outputs, path,
                           None if mesh is None else mesh.volumes_mm3))
        if "target" in result.extra:
            print(target_line([result.extra["target"]]))
    return 0


def ct_materials(rule: str, plan: Any, ct: Any, cal: Any, labels: Any  # noqa: ANN401
                 ) -> tuple[Any, Any, dict[str, object]]:
    """``--ct-materials``: (plan, labels, record) with Schneider's HU bins for the CT voxels no
    plan region claims (:mod:`tetdose.core.ct_materials`), or unchanged (density classes)."""
    from dataclasses import replace

    from tetdose.core.ct_materials import assignment_record, schneider_labels

    if rule != "schneider":
        return plan, labels, {"rule": "density-classes"}
    labels, names, comps = schneider_labels(ct, cal, labels, plan.materials)
    plan = replace(plan, materials={**plan.materials, **names},
                   compositions={**plan.compositions, **comps})
    return plan, labels, assignment_record(labels, names)


def target_line(targets: list[dict[str, Any]]) -> str:
    """What ``--target-uncertainty`` reached: the relative standard error of the mean dose in
    the target structure per run (one run, or one per phase), with the histories it took."""
    t0 = targets[0]
    of = ("the median per-cell dose" if t0.get("statistic") == "median" else "the mean dose")
    what = (f"target σ {100 * t0['uncertainty']:.3g} % of {of} in "
            f"{t0['region'] if t0['region'] is not None else 'the prescription structure'}")
    reached = [t for t in targets if t["reached"]]
    got = ", ".join(f"{100 * t['achieved']:.3g} %" for t in targets)
    hist = ", ".join(f"{t['histories']:.3g}" for t in targets)
    if len(reached) == len(targets):
        return f"{what}: reached ({got} after {hist} histories)"
    missed = len(targets) - len(reached)
    return (f"{what}: NOT reached in {missed} of {len(targets)} run(s) ({got} after {hist} "
            "histories; the --histories cap ran out: raise it)")


def summary_line(result: Any, world: str, outputs: list[str], path: Path,  # noqa: ANN401
                 tet_volume_mm3: Any = None) -> str:  # noqa: ANN401
    """The one line ``dose`` prints: histories, time, near-maximum dose in tissue, and the energy
    absorbed in and escaping the world per source particle (photons and electrons). The record
    is taken from ``result`` (its file ``path`` is only renamed into place when the command
    ends: outputs are written atomically as one)."""
    record = result.record(tet_volume_mm3)
    unit = record["units"]["dose"]
    near = record["near_max_dose_gy"]
    water = record.get("dose_to_water", {})
    to_water = (f"; dose to water per cell from the tracked electron fluence "
                f"({water['cells_fallback']} of {water['cells_dosed']} cells with dose by the "
                "per-medium fallback)" if "cells_fallback" in water else "")
    return (f"dose ({world}): {result.n_histories} histories in {result.wall_s:.1f} s; "
            f"near-max (D0.1cm³ in tissue) {near:.4g} {unit}; absorbed {result.absorbed_mev:.4g} MeV and "
            f"escaped {result.escaped_mev:.4g} MeV per particle{to_water} → {', '.join(outputs)}, "
            f"{path}")


def _run_ompmc(args: argparse.Namespace, plan: Any, settings: Any, mesh: Any, density: Any,
               labels: Any, extra: dict[str, object], progress: bool | None) -> int:  # noqa: ANN401
    """``--engine ompmc``: the dose on the CT's voxels by ompmc; with ``--mesh`` put on the tets
    by energy (:mod:`tetdose.coupling.onto_mesh`), ``dose.vtu`` beside ``dose.nrrd``."""
    from dataclasses import replace

    from tetdose.core.io import write_mesh
    from tetdose.coupling.ompmc import simulate_ompmc, simulate_ompmc_on_mesh
    from tetdose.dose.absolute import absolute_result
    from tetdose.dose.dose_to import mark
    from tetdose.transport import World

    if density is None:
        raise OptionError("--engine ompmc transports on voxels: give --ct (with --mesh too, the "
                          "dose is put on the tets)")
    if args.dask is not None:
        raise OptionError("--dask spreads tetdose's engine; ompmc runs here on OpenMP threads: "
                          "drop --dask")
    plan = plan.resolved(World(mesh=mesh, density=density, labels=labels))
    opts = ompmc_options(args)
    if mesh is None:
        main = voxel = simulate_ompmc(density, plan, settings, labels=labels, options=opts,
                                      progress=progress)
    else:
        main, voxel = simulate_ompmc_on_mesh(density, mesh, plan, settings, labels=labels,
                                             options=opts, progress=progress)
    # one prescription / calibration factor for both: fixed on the mesh when it holds regions
    by_mesh = mesh is not None and mesh.region is not None
    ref = main if by_mesh else voxel
    scaled = absolute_result(ref, plan, mesh if by_mesh else density, None if by_mesh else labels)
    added = {k: v for k, v in scaled.extra.items() if ref.extra.get(k) is not v}
    main, voxel = (replace(r.with_extra(**added), particles=r.particles * scaled.particles
                           / ref.particles) for r in (main, voxel))
    outputs: list[str] = []
    if mesh is not None:
        write_mesh(args.output, mark(main.to_mesh(mesh), settings.dose_to))
        outputs.append(str(args.output))
        extra["mesh"] = str(args.mesh)
    image_out = _sibling(args.output, ext="nrrd") if mesh is not None else args.output
    outputs += _write_images(voxel, image_out)
    world = "voxel (ompmc)" if mesh is None else "mesh (ompmc voxel energy on the tets)"
    result = main.with_extra(**extra, world=world, outputs=outputs)
    path = result.save_json(record_path(args.output), None if mesh is None else mesh.volumes_mm3)
    if not args.quiet:
        print(summary_line(result, world, outputs, path,
                           None if mesh is None else mesh.volumes_mm3))
    return 0
