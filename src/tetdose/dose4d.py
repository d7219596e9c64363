"""4D dose: photon transport on every breathing phase, accumulated on the mesh and on voxels.

Each phase p runs on its own deformed mesh (same tetrahedra, moved vertices, re-solved
densities) with the random stream ``p`` of the master seed, so phases are independent and the
run is reproducible. The mesh accumulation needs no warping because every tetrahedron keeps its
mass (:mod:`tetdose.accumulate`). Given a reference CT, each phase is also voxelized (the virtual
4D-CT density, outside the mesh the reference CT) and transported on voxels; those doses are
accumulated onto the reference grid by direct dose mapping and by energy/mass transfer, with the
motion taken from the mesh, so the three accumulations differ only by method. With a
``dask.distributed`` client the batches of every phase and geometry run on the cluster
(:mod:`tetdose.transport.distributed`), bitwise the same doses as in this process.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from tqdm.auto import tqdm

from tetdose._atomic import atomic_write_dir
from tetdose.accumulate import (
    AccumulatedDose,
    accumulate_meshes,
    direct_dose_mapping,
    energy_mass_transfer,
)
from tetdose.calibration import HUCalibration
from tetdose.errors import ImageError, MeshError
from tetdose.image import Image
from tetdose.io import write_image, write_mesh
from tetdose.mesh import TetMesh
from tetdose.motion.ct4d import phase_densities
from tetdose.motion.phases import PhaseSeries
from tetdose.prescription import prescribe_dose4d
from tetdose.transport import DoseResult, Plan, TransportSettings, simulate


@dataclass(frozen=True, eq=False)
class VoxelDose4D:
    """Per-phase voxel doses on the virtual 4D-CT and their two accumulations [Gy]."""

    density: list[Image]  # per-phase density [g/cm³] used for transport
    results: list[DoseResult]
    direct_mapping: Image  # (a) dose interpolated through the motion
    energy_mass_transfer: Image  # (b) energy and mass moved with the motion

    @property
    def doses(self) -> list[Image]:
        return [r.to_images()[0] for r in self.results]


@dataclass(frozen=True, eq=False)
class Dose4D:
    """Per-phase mesh doses, their accumulation on the reference mesh, and the voxel way."""

    series: PhaseSeries
    results: list[DoseResult]
    accumulated: AccumulatedDose
    voxel: VoxelDose4D | None

    def summary(self) -> dict[str, object]:
        """Ledger, lost photons and timing per phase, and the accumulated dose range.

        ``wall_s``: the phase's run (with dask: the whole distributed call); ``transport_s``:
        the time spent on this phase's batches (with dask: summed over its worker tasks).
        """
        return {
            "phases": [{"phase_percent": float(self.series.phase_percent[k]),
                        "ledger": r.ledger, "lost_photons": r.lost_photons,
                        "relocations": r.relocations, "wall_s": r.wall_s,
                        "transport_s": r.extra.get("task_s", r.wall_s),
                        "max_dose_gy": float(r.dose_gy.max())}
                       for k, r in enumerate(self.results)],
            "accumulated_max_dose_gy": float(self.accumulated.dose_gy.max()),
            "weights": self.accumulated.weights.tolist(),
        }


def run_dose4d(series: PhaseSeries, plan: Plan, settings: TransportSettings, *,
               ct_hu: Image | None = None, calibration: HUCalibration | None = None,
               phase_density: list[Image] | None = None, progress: bool = False,
               client: Any = None, batches_per_task: int = 1) -> Dose4D:  # noqa: ANN401
    """Transport ``plan`` on every phase of ``series`` (which must carry densities).

    With ``ct_hu`` the voxel doses on the virtual 4D-CT and their accumulations are computed too
    (``phase_density``: the phases' density images if already voxelized, see
    :func:`tetdose.motion.ct4d.phase_densities`). Phase k (mesh and voxels) draws from random
    stream k of ``settings.seed``. With a ``dask.distributed`` ``client`` every phase's batches
    (``batches_per_task`` per task) of both geometries are spread over the cluster at once
    (:func:`tetdose.transport.distributed.simulate_distributed`); the doses are bitwise those of
    the local run.
    """
    if series.density_g_cm3 is None:
        raise MeshError("the phases carry no density; run the density update first "
                        "(tetdose deform, or motion.update_series)")
    n = series.n_phases
    plan = plan.resolved(series.reference)  # isocenter = "structure" → its planning centroid
    meshes = [series.mesh(k) for k in range(n)]
    density = None
    if ct_hu is not None:
        density = phase_density or phase_densities(series, ct_hu, calibration=calibration,
                                                   progress=progress)
        if len(density) != n:
            raise ImageError(f"{len(density)} phase density images for {n} phases; give one "
                             "per phase")
    geoms: list[TetMesh | Image] = [*meshes, *(density or [])]
    streams = [replace(settings, stream=k % n) for k in range(len(geoms))]
    if client is None:
        results = [simulate(g, plan, st, progress=False) for g, st in
                   zip(tqdm(geoms, desc="dose per phase (mesh, then voxels)",
                            disable=not progress), streams, strict=True)]
    else:
        from tetdose.transport.distributed import simulate_distributed

        results = simulate_distributed(client, geoms, plan, streams,
                                       batches_per_task=batches_per_task, progress=progress)
    accumulated = accumulate_meshes(meshes, [r.dose_gy for r in results[:n]],
                                    weights=series.time_weight,
                                    dose_std_gy=[r.dose_std_gy for r in results[:n]])
    voxel = None if density is None else _voxel_way(series, density, results[n:])
    # Prescription (tetdose.prescription): one scale for every phase and accumulation.
    return prescribe_dose4d(Dose4D(series, results[:n], accumulated, voxel), plan)


def _voxel_way(series: PhaseSeries, density: list[Image],
               results: list[DoseResult]) -> VoxelDose4D:
    doses = [r.to_images()[0] for r in results]
    ref, pts, w = series.reference, series.points_mm, series.time_weight
    grid = density[0].grid
    return VoxelDose4D(density, results,
                       direct_dose_mapping(ref, pts, doses, grid, weights=w),
                       energy_mass_transfer(ref, pts, doses, density, grid, weights=w))


def write_dose4d(result: Dose4D, out_dir: str | os.PathLike[str]) -> Path:
    """Write one dose VTU (+ JSON run record) per phase, ``accumulated.vtu`` on the reference
    mesh, and with the voxel way ``voxel/`` phase doses and both accumulations; atomic."""
    out = Path(out_dir)
    with atomic_write_dir(out) as tmp:
        for k, r in enumerate(result.results):
            stem = f"phase_{result.series.phase_percent[k]:05.1f}"
            write_mesh(tmp / f"{stem}.vtu", r.to_mesh(result.series.mesh(k)))
            r.save_json(tmp / f"{stem}.json")
        acc = result.accumulated
        write_mesh(tmp / "accumulated.vtu", result.series.reference.with_data(cell_data={
            "dose": acc.dose_gy, "dose_std": acc.dose_std_gy if acc.dose_std_gy is not None
            else np.zeros_like(acc.dose_gy), "mass_g": acc.mass_g}))
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
        (tmp / "summary.json").write_text(json.dumps(result.summary(), indent=2) + "\n")
    return out
