"""Monte Carlo photon transport on a tetrahedral mesh (linear density) and on a voxel grid.

Model in, results out (OpenMC style)::

    plan = Plan((PhotonSource("pencil", [0, 0, -50], [0, 0, 1], energies_mev=[1.0]),))
    result = simulate(mesh, plan, TransportSettings(n_histories=100_000))
    result.dose_gy, result.dose_std_gy, result.ledger

``geometry`` is a :class:`~tetdose.mesh.TetMesh` with point_data ``density`` [g/cm³] (and
optional ``region`` labels), or an :class:`~tetdose.image.Image` of densities [g/cm³] (with an
optional label image). The same sources, physics, random streams and tallies run on both.
Materials: region label → name from ``plan.materials``; any other cell takes its density class
(:func:`tetdose.transport.xs.material_for_density`, Schneider-style).

Runs go batch group by batch group (numba threads over the batches of a group; a tqdm bar for
runs longer than :data:`PROGRESS_DELAY_S`). :func:`run_batches` is the unit of work that
:mod:`tetdose.transport.distributed` ships to dask workers for the same, bitwise, result.
"""

from __future__ import annotations

import time
import warnings
from typing import NamedTuple

import numba
import numpy as np
from tqdm.auto import tqdm

from tetdose._typing import FloatArray, IntArray
from tetdose.errors import ImageError, MeshError, PlanError
from tetdose.image import Image, ImageGrid
from tetdose.mesh import TetMesh
from tetdose.transport._geometry_tet import TetGeometry
from tetdose.transport._geometry_voxel import VoxelGeometry
from tetdose.transport._history import N_COUNTS, N_LEDGER
from tetdose.transport._run import run_mesh, run_voxel
from tetdose.transport._source import SourceArrays
from tetdose.transport.geometry import mesh_geometry, morton_order
from tetdose.transport.model import PhotonSource, Plan, TransportSettings
from tetdose.transport.result import DoseResult
from tetdose.transport.source import E_MAX_MEV, source_arrays
from tetdose.transport.xs import (
    DENSITY_CLASS_MATERIALS,
    CrossSections,
    build_cross_sections,
    material_for_density,
)

__all__ = ["DoseResult", "PhotonSource", "Plan", "TransportSettings", "mesh_geometry",
           "morton_order", "run_mesh_transport", "run_voxel_transport", "simulate"]

#: Batches per kernel call and thread (groups keep the progress bar moving).
BATCH_GROUP_PER_THREAD = 2
#: The progress bar appears only for runs longer than this [s].
PROGRESS_DELAY_S = 2.0


def simulate(geometry: TetMesh | Image, plan: Plan, settings: TransportSettings, *,
             labels: Image | None = None, progress: bool | None = None) -> DoseResult:
    """Run ``plan`` on a mesh (dose per tetrahedron) or a density image (dose per voxel)."""
    if isinstance(geometry, TetMesh):
        return run_mesh_transport(geometry, plan, settings, progress=progress)
    if isinstance(geometry, Image):
        return run_voxel_transport(geometry, plan, settings, labels=labels, progress=progress)
    raise PlanError(f"geometry must be a TetMesh or an Image of densities, got {type(geometry)}")


def _assign_materials(mean_density: FloatArray, region: IntArray | None,
                      plan: Plan) -> tuple[IntArray, list[str]]:
    """Material index per cell and the material names (only those used)."""
    names = list(DENSITY_CLASS_MATERIALS)
    mat = material_for_density(mean_density).astype(np.intp)
    if plan.materials and region is None:
        warnings.warn("plan [materials] given but the geometry has no region labels; "
                      "every cell gets its density-class material", stacklevel=3)
    elif region is not None:
        for label, name in plan.materials.items():
            if name not in names:
                names.append(name)
            mat[region == label] = names.index(name)
    used, mat = np.unique(mat, return_inverse=True)
    return np.ascontiguousarray(mat.astype(np.intp)), [names[i] for i in used]


def _mesh_job(mesh: TetMesh, plan: Plan, settings: TransportSettings,
              density_g_cm3: FloatArray | None) -> _Job:
    if density_g_cm3 is None:
        if "density" not in mesh.point_data:
            raise MeshError("the mesh has no point_data 'density' (g/cm³); map a CT onto it "
                            "first (tetdose map) or pass density_g_cm3")
        density_g_cm3 = mesh.point_data["density"]
    rho = np.asarray(density_g_cm3, dtype=np.float64).reshape(-1)
    settings.check_tally_size(mesh.n_tets)
    mean_rho = rho[mesh.tets].mean(axis=1) if len(rho) == mesh.n_points else rho
    material, names = _assign_materials(mean_rho, mesh.region, plan)
    order = morton_order(mesh.centroids_mm)
    geom = mesh_geometry(mesh, rho, material, order)
    mass_g = mesh.volumes_mm3 * mean_rho / 1000.0
    return _Job("mesh", geom, names, source_arrays(plan, settings), mass_g, order, None)


def _voxel_job(density: Image, plan: Plan, settings: TransportSettings,
               labels: Image | None) -> _Job:
    grid = density.grid
    rho = np.ascontiguousarray(density.array, dtype=np.float64).reshape(-1)
    if not np.all(np.isfinite(rho)) or np.any(rho < 0):
        raise ImageError("the density image must hold finite values ≥ 0 g/cm³; "
                         "convert HU to density first (HUCalibration)")
    region = None
    if labels is not None:
        grid.require_same(labels.grid, "density and label images")
        region = np.asarray(labels.array).reshape(-1).astype(np.int64)
    settings.check_tally_size(grid.n_voxels)
    material, names = _assign_materials(rho, region, plan)
    spacing = grid.spacing_mm
    geom = VoxelGeometry(-0.5 * spacing, spacing.copy(), np.array(grid.size, dtype=np.intp),
                         rho, material)

    def to_frame(a: FloatArray, is_dir: bool) -> FloatArray:
        return a @ grid.direction if is_dir else grid.to_grid_frame(a)

    mass_g = rho * grid.voxel_volume_mm3 / 1000.0
    return _Job("voxel", geom, names, source_arrays(plan, settings, to_frame), mass_g, None, grid)


def run_mesh_transport(mesh: TetMesh, plan: Plan, settings: TransportSettings, *,
                       density_g_cm3: FloatArray | None = None,
                       progress: bool | None = None) -> DoseResult:
    """Dose per tetrahedron; density from ``density_g_cm3`` or point_data ``density``.

    Tets are walked in Morton order (:func:`morton_order`); the result is in mesh order.
    """
    return _execute(_mesh_job(mesh, plan, settings, density_g_cm3), plan, settings, progress)


def run_voxel_transport(density: Image, plan: Plan, settings: TransportSettings, *,
                        labels: Image | None = None, progress: bool | None = None) -> DoseResult:
    """Dose per voxel on a density image [g/cm³] (constant density per voxel)."""
    return _execute(_voxel_job(density, plan, settings, labels), plan, settings, progress)


class _Job(NamedTuple):
    """Everything a batch run needs (picklable, for dask workers too)."""

    kind: str  # "mesh" | "voxel"
    geom: TetGeometry | VoxelGeometry
    names: list[str]
    src: SourceArrays
    mass_g: FloatArray
    order: IntArray | None  # kernel cell i is geometry cell order[i] (mesh only)
    grid: ImageGrid | None


def _cross_sections(job: _Job, settings: TransportSettings) -> CrossSections:
    """Read-only tables for ``job``, cached by name: runs with the same materials and cut-off
    (breathing phases, mesh and voxel engine) share one build."""
    return build_cross_sections(job.names, e_min_mev=min(0.01, settings.energy_cutoff_mev),
                                e_max_mev=E_MAX_MEV)


def run_batches(job: _Job, xs: CrossSections, settings: TransportSettings, b_start: int,
                b_stop: int) -> tuple[FloatArray, FloatArray, IntArray]:
    """Rows ``b_start … b_stop−1`` of (energy [MeV], ledger [MeV], counters), kernel cell order.

    Each row depends only on the seed, the batch index and the inputs (counter-based streams),
    so rows computed anywhere (threads, processes, dask workers) are bitwise the same.
    """
    kernel = run_mesh if job.kind == "mesh" else run_voxel
    n = b_stop - b_start
    energy = np.zeros((n, len(job.mass_g)))
    ledger = np.zeros((n, N_LEDGER))
    counts = np.zeros((n, N_COUNTS), dtype=np.int64)
    kernel(job.geom, xs, job.src, settings.seed, settings.stream, settings.n_histories,
           settings.n_batches, b_start, b_stop, settings.energy_cutoff_mev,
           settings.estimator == "track_length", energy, ledger, counts)
    return energy, ledger, counts


def _execute(job: _Job, plan: Plan, settings: TransportSettings,
             progress: bool | None) -> DoseResult:
    """Run all batches locally in groups (so the progress bar moves) and assemble the result."""
    xs = _cross_sections(job, settings)
    nb = settings.n_batches
    group = BATCH_GROUP_PER_THREAD * max(1, numba.get_num_threads())
    rows = []
    t0, cpu0 = time.perf_counter(), time.process_time()
    with tqdm(total=nb, unit="batch", disable=None if progress is None else not progress,
              desc=f"{job.kind} transport", delay=PROGRESS_DELAY_S) as bar:
        for b0 in range(0, nb, group):
            b1 = min(nb, b0 + group)
            rows.append(run_batches(job, xs, settings, b0, b1))
            bar.update(b1 - b0)
    result = _assemble(job, plan, settings, rows, time.perf_counter() - t0)
    result.extra["cpu_s"] = time.process_time() - cpu0  # all threads of this process
    return result


def _assemble(job: _Job, plan: Plan, settings: TransportSettings,
              rows: list[tuple[FloatArray, FloatArray, IntArray]], wall_s: float) -> DoseResult:
    """DoseResult from batch rows in batch order (tally moved back to geometry cell order)."""
    from tetdose import __version__

    energy = np.concatenate([r[0] for r in rows])
    if job.order is not None:
        energy[:, job.order] = energy.copy()
    ledger = np.concatenate([r[1] for r in rows])
    counts = np.concatenate([r[2] for r in rows])
    nb = settings.n_batches
    per_batch = np.diff(np.arange(nb + 1) * settings.n_histories // nb)
    result = DoseResult(energy, per_batch, job.mass_g, ledger, counts, plan.particles,
                        settings.seed, settings.estimator, job.kind, wall_s, __version__,
                        job.grid, {"materials": job.names, "n_cells": len(job.mass_g)})
    if result.lost_photons > 1e-4 * settings.n_histories:
        warnings.warn(f"{result.lost_photons} photons were lost in the geometry "
                      f"({result.relocations} relocations); check the mesh", stacklevel=3)
    return result
