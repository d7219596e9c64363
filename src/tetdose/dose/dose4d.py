"""4D dose: photon transport on every breathing phase, accumulated on the mesh and on voxels.

Each phase p runs on its own deformed mesh (same tetrahedra, moved vertices, re-solved
densities) with the random stream ``p`` of the master seed, so phases are independent and the
run is reproducible. The mesh accumulation needs no warping because every tetrahedron keeps its
mass (:mod:`tetdose.dose.accumulate`).

**The body of each phase.** Without a CT the mesh is alone in vacuum. With a reference CT the
mesh runs inside the phase's body (the hybrid world, :mod:`tetdose.transport.geometry.world`), and the
voxel-only reference dose of the phase is computed on exactly that body:

  * ``phase_ct`` given (a real 4D-CT, one CT per phase on one grid): that phase's CT;
  * ``dvfs`` given (the phases came from displacement fields): the virtual phase CT with the
    reference CT warped by the phase's DVF outside the mesh;
  * otherwise the virtual phase CT of :func:`tetdose.motion.ct4d.phase_densities`: the mesh
    voxelized (mass-exact) and, outside it, the reference CT unmoved — voxels the moving mesh
    leaves get the reference CT's density back, voxels it enters are partly mesh (as ``4dct``).

**Compositions of the bodies** (``ct_materials``, as ``tetdose dose --ct``): Schneider's HU →
composition bins (default; :mod:`tetdose.core.ct_materials`) from each phase's HU — the phase CT's
own (``phase_ct``), else the reference CT's where the body is the reference CT unmoved and the
calibration's inverse elsewhere (:func:`tetdose.core.ct_materials.body_hu`) — or the five density
classes (``"density-classes"``). The mesh's tets keep the plan's regions and density classes.

In the hybrid world a voxel cut by the mesh surface is transported with its body density on the
part outside the mesh. The voxel part accumulates per voxel, ΣwE/Σwm (exact when the tissue
outside the mesh does not move, i.e. the reference-CT body); the voxel-only reference doses are
accumulated onto the reference grid by direct dose mapping and by energy/mass transfer, with the
motion taken from the mesh, so the accumulations differ only by method. With a
``dask.distributed`` client the batches of every phase and geometry run on the cluster
(:mod:`tetdose.transport.run.distributed`), bitwise the same doses as in this process. A target
uncertainty is about a structure of the mesh: each phase's hybrid run stops at it, and the
phase's voxel-only run then takes the same histories (the same source particles).
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from tetdose._atomic import atomic_write_dir
from tetdose._constants import MM3_PER_CM3
from tetdose.core.body import NEAR_MAX_SAID, near_max_gy
from tetdose.core.calibration import HUCalibration
from tetdose.core.ct_materials import CT_MATERIAL_RULES, body_hu, schneider_bodies
from tetdose.core.image import Image
from tetdose.core.io import write_image, write_mesh
from tetdose.core.mesh import TetMesh
from tetdose.dose.absolute import absolute_dose4d
from tetdose.dose.accumulate import (
    AccumulatedDose,
    accumulate_meshes,
    accumulate_static_voxels,
    direct_dose_mapping,
    energy_mass_transfer,
)
from tetdose.dose.dose_to import mark
from tetdose.errors import ImageError, MeshError, OptionError
from tetdose.motion.ct4d import phase_densities
from tetdose.motion.dvf import DisplacementField
from tetdose.motion.phases import PhaseSeries
from tetdose.transport import DoseResult, Plan, TransportSettings, World
from tetdose.transport.run.distributed import simulate_on

#: A voxel transport engine for :func:`run_dose4d`: (phase density [g/cm³], phase mesh, plan,
#: settings) → (mesh result, voxel result).
VoxelEngine = Callable[[Image, TetMesh, Plan, TransportSettings], tuple[DoseResult, DoseResult]]


@dataclass(frozen=True, eq=False)
class VoxelDose4D:
    """Per-phase voxel doses on the virtual 4D-CT and their two accumulations [Gy]."""

    density: list[Image]  # per-phase density [g/cm³] used for transport
    results: list[DoseResult]
    direct_mapping: Image  # (a) dose interpolated through the motion
    energy_mass_transfer: Image  # (b) energy and mass moved with the motion
    direct_mapping_std: Image | None = None  # σ of (a) and (b) [Gy], see _voxel_way
    energy_mass_transfer_std: Image | None = None

    @property
    def doses(self) -> list[Image]:
        return [r.to_images()[0] for r in self.results]


@dataclass(frozen=True, eq=False)
class BodyDose4D:
    """The voxel part of hybrid phase runs (the body outside the mesh), accumulated per voxel
    (ΣwE/Σwm), and the combined accumulated dose on the CT grid (mesh energy put on the voxels
    through the exact overlaps of the reference mesh) [Gy]."""

    accumulated: Image
    accumulated_std: Image
    combined: Image


@dataclass(frozen=True, eq=False)
class Dose4D:
    """Per-phase mesh (or hybrid) doses, their accumulation on the reference mesh, the body's
    voxel part (hybrid runs) and the voxel-only way."""

    series: PhaseSeries
    results: list[DoseResult]
    accumulated: AccumulatedDose
    voxel: VoxelDose4D | None
    body: BodyDose4D | None = None
    #: The delivery in time when the phases got only their share of it (dose.interplay).
    delivery: dict[str, object] | None = None
    #: How the bodies' voxels got their compositions (run_dose4d's ``ct_materials``).
    ct_materials: dict[str, object] | None = None

    @property
    def dose_to(self) -> str:
        """"medium" or "water" (:mod:`tetdose.dose.dose_to`), as the phases' runs report."""
        return str(self.results[0].extra.get("dose_to", "medium"))

    def summary(self) -> dict[str, object]:
        """Ledger, lost photons, timing and the near-maximum dose in tissue (D0.1cm³,
        :func:`tetdose.core.body.near_max_gy`) per phase, the accumulated near-maxima, and what
        the dose is (to medium or to water).

        ``wall_s``: the phase's run (with dask: the whole distributed call); ``transport_s``:
        the time spent on this phase's batches (with dask: summed over its worker tasks).
        """
        ref_cm3 = self.series.reference.volumes_mm3 / MM3_PER_CM3
        out: dict[str, object] = {
            "world": self.results[0].geometry,
            "physics": self.results[0].extra.get("physics", "kerma"),
            "phases": [{"phase_percent": float(self.series.phase_percent[k]),
                        "ledger": r.ledger, "lost_photons": r.lost_photons,
                        "relocations": r.relocations, "wall_s": r.wall_s,
                        "transport_s": r.extra.get("task_s", r.wall_s),
                        "near_max_dose_gy": r.mesh_part().near_max_dose_gy(
                            self.series.mesh(k).volumes_mm3),
                        "mesh_voxel_switches": int(r.counts_per_batch[:, 5].sum()),
                        **({"target": r.extra["target"]} if "target" in r.extra else {}),
                        **({"dose_to_water": r.extra["dose_to_water"]}
                           if "dose_to_water" in r.extra else {})}
                       for k, r in enumerate(self.results)],
            "accumulated_near_max_dose_gy": near_max_gy(
                self.accumulated.dose_gy, ref_cm3, self.accumulated.mass_g / ref_cm3),
            "near_max": NEAR_MAX_SAID,
            "weights": self.accumulated.weights.tolist(),
            "units": {"dose": self.results[0].record()["units"]["dose"]},
            "dose_to": self.dose_to,
        }
        if "source_mix" in self.results[0].extra:  # beams and volume sources in one plan
            out["source_mix"] = self.results[0].extra["source_mix"]
        if "dose_to_water" in self.results[0].extra:
            out["dose_to_water"] = self.results[0].extra["dose_to_water"]
        if self.delivery is not None:
            out["delivery"] = self.delivery
        if self.ct_materials is not None:
            out["ct_materials"] = self.ct_materials
        if self.body is not None:  # densities of phase 0's voxels (mesh and body together)
            vox = self.results[0].combined()
            cm3 = vox.grid.voxel_volume_mm3 / MM3_PER_CM3
            for key, img in (("body_accumulated", self.body.accumulated),
                             ("combined_accumulated", self.body.combined)):
                out[f"{key}_near_max_dose_gy"] = near_max_gy(img.array, cm3, vox.mass_g / cm3)
        return out


def run_dose4d(series: PhaseSeries, plan: Plan, settings: TransportSettings, *,
               ct_hu: Image | None = None, calibration: HUCalibration | None = None,
               phase_density: list[Image] | None = None, phase_ct: list[Image] | None = None,
               dvfs: list[DisplacementField] | None = None, progress: bool = False,
               client: Any = None, batches_per_task: int = 1,  # noqa: ANN401
               voxel_engine: VoxelEngine | None = None,
               phase_plans: Sequence[Plan] | None = None,
               phase_settings: Sequence[TransportSettings] | None = None,
               ct_materials: str = "schneider") -> Dose4D:
    """Transport ``plan`` on every phase of ``series`` (which must carry densities).

    With ``ct_hu`` every phase runs in the hybrid world — the phase mesh inside the phase's body
    (module docstring: ``phase_ct`` HU images of a real 4D-CT, else the virtual phase CT, with
    ``dvfs`` warping the reference CT outside the mesh) — and the voxel-only doses on the same
    bodies and their accumulations are computed too (``phase_density``: the bodies' density
    images if already computed). Phase k (hybrid and voxels) draws from random stream k of
    ``settings.seed``. With a ``dask.distributed`` ``client`` every phase's batches
    (``batches_per_task`` per task) of both geometries are spread over the cluster at once
    (:func:`tetdose.transport.run.distributed.simulate_distributed`); the doses are bitwise those of
    the local run.

    ``voxel_engine`` (e.g. :func:`tetdose.coupling.ompmc.phase_engine`) replaces tetdose's
    transport: it runs on each phase's body CT (``ct_hu`` or ``phase_ct`` required) and returns
    (the phase's mesh result, its voxel result) — the voxel dose put on the tets by energy — which
    are accumulated as tetdose's own (the voxel way too; there is no hybrid body part).

    ``phase_plans`` / ``phase_settings`` (one per phase, e.g. from :mod:`tetdose.dose.interplay`):
    phase k transports its own plan with its own settings (histories and stream as given)
    instead of ``plan`` with stream k; the absolute scale still comes from ``plan``.

    ``ct_materials``: the compositions of the bodies' voxels, ``"schneider"`` (default) or
    ``"density-classes"`` (module docstring; recorded in :meth:`Dose4D.summary`).
    """
    if ct_materials not in CT_MATERIAL_RULES:
        raise OptionError(f"ct_materials must be one of {CT_MATERIAL_RULES}, got {ct_materials!r}")
    if series.density_g_cm3 is None:
        raise MeshError("the phases carry no density; run the density update first "
                        "(tetdose deform, or motion.update_series)")
    n = series.n_phases
    plan = plan.resolved(series.reference)  # isocenter = "structure" → its planning centroid
    meshes = [series.mesh(k) for k in range(n)]
    density = None
    if ct_hu is not None or phase_ct is not None:
        density = phase_density or _bodies(series, ct_hu, phase_ct, dvfs, calibration, progress)
        if len(density) != n:
            raise ImageError(f"{len(density)} phase density images for {n} phases; give one "
                             "per phase")
        for img in density[1:]:
            density[0].grid.require_same(img.grid, "the phase CTs")
    plans = [plan] * n if phase_plans is None else list(phase_plans)
    sets = ([replace(settings, stream=k) for k in range(n)] if phase_settings is None
            else list(phase_settings))
    if len(plans) != n or len(sets) != n:
        raise MeshError(f"{len(plans)} plans and {len(sets)} settings for {n} phases; give "
                        "one per phase")
    if voxel_engine is not None:
        return _with_engine(series, plan, plans, sets, meshes, density, voxel_engine)
    labels: list[Image | None] = [None] * n
    record = None
    if density is not None:
        record = {"rule": ct_materials}
        if ct_materials == "schneider":
            labels, plan, plans, record = _schneider(density, ct_hu, phase_ct, calibration, plan,
                                                     plans)
    worlds = [World(mesh=m, density=None if density is None else density[k], labels=labels[k])
              for k, m in enumerate(meshes)]
    geoms: list[World | TetMesh | Image] = [
        *worlds, *(World(density=d, labels=lab) if lab is not None else d
                   for d, lab in zip(density or [], labels, strict=False))]
    if phase_plans is not None:
        each = [simulate_on(client, [geoms[k], *([geoms[n + k]] if density else [])], plans[k],
                            sets[k], batches_per_task=batches_per_task, progress=False)
                for k in range(n)]
        results = [r[0] for r in each] + [r[1] for r in each if len(r) > 1]
    elif settings.target_uncertainty is not None and density is not None:
        streams = [replace(settings, stream=k % n) for k in range(len(geoms))]
        results = _to_target(client, geoms, plan, streams, n, progress)
    else:
        streams = [replace(settings, stream=k % n) for k in range(len(geoms))]
        results = simulate_on(client, geoms, plan, streams, batches_per_task=batches_per_task,
                              progress=progress, desc="dose per phase (mesh, then voxels)")
    parts = [r.mesh_part() for r in results[:n]]
    accumulated = accumulate_meshes(meshes, [r.dose_gy for r in parts],
                                    weights=series.time_weight,
                                    dose_std_gy=[r.dose_std_gy for r in parts])
    voxel = body = None
    if density is not None:
        voxel = _voxel_way(series, density, results[n:])
        body = _body_way(series, accumulated, results[:n])
    # Prescription (tetdose.plan.prescription): one scale for every phase and accumulation.
    return absolute_dose4d(Dose4D(series, results[:n], accumulated, voxel, body,
                                  ct_materials=record), plan)


def _schneider(density: list[Image], ct_hu: Image | None, phase_ct: list[Image] | None,
               calibration: HUCalibration | None, plan: Plan, plans: list[Plan]
               ) -> tuple[list[Image | None], Plan, list[Plan], dict[str, object]]:
    """Schneider labels of the phase bodies, the plans with their compositions, the record."""
    cal = calibration or HUCalibration.schneider2000()
    if phase_ct is not None:
        hu, said = list(phase_ct), "the phase CTs"
    else:
        hu = [body_hu(d, cal, ct_hu) for d in density]
        said = ("the reference CT where the body is it unmoved, else the calibration's inverse "
                "(lowest HU of the density)")
    labels, names, comps, record = schneider_bodies(hu, cal, said)

    def add(p: Plan) -> Plan:
        return replace(p, materials={**p.materials, **names},
                       compositions={**p.compositions, **comps})

    return list(labels), add(plan), [add(p) for p in plans], record


def _to_target(client: Any, geoms: list[World | TetMesh | Image], plan: Plan,  # noqa: ANN401
               streams: list[TransportSettings], n: int, progress: bool) -> list[DoseResult]:
    """Phases run to their target uncertainty (of a structure of the mesh) in the hybrid world;
    each phase's voxel-only run (no structures) then gets the batches and histories its hybrid
    run took (the same source particles: stream k), so both ways compare at the same
    statistics."""
    hybrid = simulate_on(client, geoms[:n], plan, streams[:n], progress=progress,
                         desc="dose per phase (mesh)")
    same = [replace(st, target_uncertainty=None, target_region=None, n_histories=r.n_histories,
                    n_batches=r.n_batches) for st, r in zip(streams[n:], hybrid, strict=True)]
    return [*hybrid, *simulate_on(client, geoms[n:], plan, same, progress=progress,
                                  desc="dose per phase (voxels)")]


def _with_engine(series: PhaseSeries, plan: Plan, plans: list[Plan],
                 sets: list[TransportSettings], meshes: list[TetMesh],
                 density: list[Image] | None, engine: VoxelEngine) -> Dose4D:
    """Every phase's body CT through ``engine`` (its plan and settings), accumulated."""
    if density is None:
        raise ImageError("the voxel engine runs on each phase's CT: give the reference CT "
                         "(--like) or the phase CTs (--ct4d)")
    pairs = [engine(density[k], m, plans[k], sets[k]) for k, m in enumerate(meshes)]
    results = [p[0] for p in pairs]
    accumulated = accumulate_meshes(meshes, [r.dose_gy for r in results],
                                    weights=series.time_weight,
                                    dose_std_gy=[r.dose_std_gy for r in results])
    voxel = _voxel_way(series, density, [p[1] for p in pairs])
    return absolute_dose4d(Dose4D(series, results, accumulated, voxel, None, ct_materials={
        "rule": "engine", "note": "the voxel engine chose the bodies' media (ompmc: PEGS "
        "media by density)"}), plan)


def _bodies(series: PhaseSeries, ct_hu: Image | None, phase_ct: list[Image] | None,
            dvfs: list[DisplacementField] | None, calibration: HUCalibration | None,
            progress: bool) -> list[Image]:
    """The density [g/cm³] of every phase's body (module docstring)."""
    cal = calibration or HUCalibration.schneider2000()
    if phase_ct is not None:
        return [Image(cal.density_checked(ct.array, f"4D-CT phase {k}")[0].astype(np.float64),
                      ct.grid) for k, ct in enumerate(phase_ct)]
    return phase_densities(series, ct_hu, calibration=cal, dvfs=dvfs, progress=progress)


def _body_way(series: PhaseSeries, accumulated: AccumulatedDose,
              results: list[DoseResult]) -> BodyDose4D:
    """Voxel part accumulated per voxel, and the combined (mesh + voxel) dose on the grid."""
    from tetdose.core.transfer import mesh_dose_to_grid, mesh_mass_on_grid

    grid = results[0].grid
    parts = [r.voxel_part() for r in results]
    dose, std, mass = accumulate_static_voxels(
        [p.dose_gy for p in parts], [p.mass_g for p in parts], weights=series.time_weight,
        dose_std_gy=[p.dose_std_gy for p in parts])
    ref = series.reference.with_data(point_data={"density": series.density_g_cm3[0]})
    mesh_dose = mesh_dose_to_grid(ref, accumulated.dose_gy, grid).array.ravel()
    mesh_mass = mesh_mass_on_grid(ref, grid).array.ravel()
    total = mass + mesh_mass
    combined = np.divide(dose * mass + mesh_dose * mesh_mass, total, out=np.zeros_like(total),
                         where=total > 0)
    shape = grid.shape
    return BodyDose4D(Image(dose.reshape(shape), grid),
                      Image((std if std is not None else np.zeros_like(dose)).reshape(shape),
                            grid), Image(combined.reshape(shape), grid))


def _voxel_way(series: PhaseSeries, density: list[Image],
               results: list[DoseResult]) -> VoxelDose4D:
    """Both voxel accumulations and their σ: each phase's voxel variance σ_p² carried the same
    way, Σ_p w_p² σ_p² (phases independent) — exact for the direct mapping up to its trilinear
    interpolation (an upper bound), approximate for the energy/mass transfer (the phases' masses
    in a voxel taken equal, the sub-voxel averaging ignored: an upper bound too)."""
    images = [r.to_images() for r in results]
    doses, var = [d for d, _ in images], [s.array**2 for _, s in images]
    ref, pts, w = series.reference, series.points_mm, series.time_weight
    grid = density[0].grid
    wn = np.asarray(w, dtype=np.float64) / np.sum(w)
    scaled = [Image(len(wn) * wp**2 * v, grid) for wp, v in zip(wn, var, strict=True)]
    ddm_var = direct_dose_mapping(ref, pts, scaled, grid)  # equal weights 1/K: Σ_p w_p² σ_p²
    emt_var = energy_mass_transfer(ref, pts, scaled, density, grid)
    return VoxelDose4D(density, results,
                       direct_dose_mapping(ref, pts, doses, grid, weights=w),
                       energy_mass_transfer(ref, pts, doses, density, grid, weights=w),
                       Image(np.sqrt(ddm_var.array), grid), Image(np.sqrt(emt_var.array), grid))


def write_dose4d(result: Dose4D, out_dir: str | os.PathLike[str]) -> Path:
    """Write one dose VTU (+ JSON run record) per phase, ``accumulated.vtu`` on the reference
    mesh; for hybrid runs ``body/`` (per-phase combined dose images, the voxel part accumulated
    and ``accumulated_combined.nrrd``); with the voxel way ``voxel/`` phase doses and both
    accumulations; atomic."""
    out = Path(out_dir)
    with atomic_write_dir(out) as tmp:
        for k, r in enumerate(result.results):
            stem = f"phase_{result.series.phase_percent[k]:05.1f}"
            write_mesh(tmp / f"{stem}.vtu",
                       mark(r.to_mesh(result.series.mesh(k)), result.dose_to))
            r.save_json(tmp / f"{stem}.json", result.series.mesh(k).volumes_mm3)
        acc = result.accumulated
        write_mesh(tmp / "accumulated.vtu", mark(result.series.reference.with_data(cell_data={
            "dose": acc.dose_gy, "dose_std": acc.dose_std_gy if acc.dose_std_gy is not None
            else np.zeros_like(acc.dose_gy), "mass_g": acc.mass_g}), result.dose_to))
        if result.body is not None:
            body = tmp / "body"
            for k, r in enumerate(result.results):
                stem = f"phase_{result.series.phase_percent[k]:05.1f}"
                write_image(body / f"{stem}_combined_dose.nrrd", r.to_images()[0])
            write_image(body / "accumulated_voxel_part.nrrd", result.body.accumulated)
            write_image(body / "accumulated_voxel_part_std.nrrd", result.body.accumulated_std)
            write_image(body / "accumulated_combined.nrrd", result.body.combined)
        if result.voxel is not None:
            vox = tmp / "voxel"
            for k, r in enumerate(result.voxel.results):
                stem = f"phase_{result.series.phase_percent[k]:05.1f}"
                dose, std = r.to_images()
                write_image(vox / f"{stem}_dose.nrrd", dose)
                write_image(vox / f"{stem}_dose_std.nrrd", std)
                r.save_json(vox / f"{stem}.json")
            write_image(vox / "accumulated_direct_mapping.nrrd", result.voxel.direct_mapping)
            write_image(vox / "accumulated_energy_mass_transfer.nrrd",
                        result.voxel.energy_mass_transfer)
            for stem, std in (("direct_mapping", result.voxel.direct_mapping_std),
                              ("energy_mass_transfer", result.voxel.energy_mass_transfer_std)):
                if std is not None:  # σ beside each, for `tetdose compare`
                    write_image(vox / f"accumulated_{stem}_std.nrrd", std)
        (tmp / "summary.json").write_text(json.dumps(result.summary(), indent=2) + "\n")
    return out
