"""Monte Carlo photon transport on a tetrahedral mesh (linear density) and on a voxel grid.

Model in, results out (OpenMC style)::

    plan = Plan((PhotonSource("pencil", [0, 0, -50], [0, 0, 1], energies_mev=[1.0]),))
    result = simulate(mesh, plan, TransportSettings(n_histories=100_000))
    result.dose_gy, result.dose_std_gy, result.ledger

``geometry`` is a :class:`~tetdose.transport.geometry.world.World` — a
:class:`~tetdose.core.mesh.TetMesh` with point_data ``density`` [g/cm³] (and optional ``region``
labels) inside an :class:`~tetdose.core.image.Image` of densities [g/cm³] (with an optional label
image), either part alone — or a bare mesh or density image. One history loop serves every
world (mesh-only and voxel-only are worlds with one part empty).
Materials: region label → name from ``plan.materials``; any other cell takes its density class
(:func:`tetdose.transport.physics.xs.material_for_density`, Schneider-style).

Runs go batch group by batch group (numba threads over the batches of a group; a tqdm bar for
runs longer than :data:`PROGRESS_DELAY_S`). :func:`tetdose.transport.run.job.run_batches` is the
unit of work that :mod:`tetdose.transport.run.distributed` ships to dask workers for the same,
bitwise, result.

Subpackages, in the order a history meets them: :mod:`.sources` (source particles),
:mod:`.geometry` (tets, voxels, the hybrid world), :mod:`.physics` (materials, interaction data
and sampling), :mod:`.history` (the history loop, tallies, :class:`DoseResult`), :mod:`.run`
(settings, jobs, batches, dask). The plan it runs comes from :mod:`tetdose.plan`.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from tetdose.core.image import Image
from tetdose.core.mesh import TetMesh
from tetdose.errors import PlanError
from tetdose.plan.model import Plan
from tetdose.plan.photon_source import PhotonSource
from tetdose.plan.prescription import region_cells, region_label
from tetdose.transport.geometry.tets import mesh_geometry, morton_order
from tetdose.transport.geometry.world import World, as_world
from tetdose.transport.history.result import DoseResult
from tetdose.transport.run.job import build_job, execute
from tetdose.transport.run.settings import TransportSettings

__all__ = ["DoseResult", "PhotonSource", "Plan", "TransportSettings", "World", "as_world",
           "mesh_geometry", "morton_order", "resolved_target", "run_mesh_transport", "run_voxel_transport",
           "simulate"]


def simulate(geometry: TetMesh | Image | World, plan: Plan, settings: TransportSettings, *,
             labels: Image | None = None, progress: bool | None = None) -> DoseResult:
    """Run ``plan`` in a world: dose per tetrahedron, per voxel, or both (hybrid).

    Parameters
    ----------
    geometry : World, TetMesh or Image
        Where the particles travel: a :class:`World` (a mesh inside a density image: the hybrid
        world), a mapped :class:`TetMesh` (point_data ``density`` [g/cm³], in vacuum) or a
        density :class:`Image` [g/cm³] (the voxel engine).
    plan : Plan
        The sources (beams), region names, materials and prescription.
    settings : TransportSettings
        Histories, batches, seed, physics (``"dose"`` with electrons, or ``"kerma"``), cut-offs
        [MeV], tallies and variance reduction.
    labels : Image, optional
        Region labels of a density image (materials and structures of the voxels).
    progress : bool, optional
        Show a progress bar (default: when the run is long).

    Returns
    -------
    DoseResult
        Dose per source particle [Gy] and its standard deviation from the batches, per
        tetrahedron and/or per voxel (``mesh_part()``, ``to_images()``), with the energy ledger
        [MeV] and the run record.

    Raises
    ------
    TetdoseError
        Inputs that cannot be run (a beam reaching no cell, a plan naming an unknown region,
        settings out of range), each with a one-line message naming the fix.
    """
    world = as_world(geometry, labels)
    settings = resolved_target(settings, plan)
    job, on_grid = build_job(world, plan, settings)
    return execute(job, on_grid, plan, settings, progress, target_cells(world, plan, settings))


def resolved_target(settings: TransportSettings, plan: Plan) -> TransportSettings:
    """``settings`` with the structure of its target uncertainty named (``target_region``,
    else the prescription's structure), so that the run records the region it used."""
    if (settings.target_uncertainty is None or settings.target_region is not None
            or plan.prescription is None):
        return settings
    return replace(settings, target_region=plan.prescription.structure)


def target_cells(world: World, plan: Plan, settings: TransportSettings) -> np.ndarray | None:
    """Cells (mesh order, then voxels) of the structure whose mean dose the run's
    ``target_uncertainty`` is about: ``settings.target_region``, else the prescription's."""
    if settings.target_uncertainty is None:
        return None
    name = settings.target_region
    if name is None:
        if plan.prescription is None:
            raise PlanError("a target uncertainty needs a structure: give --target-region NAME "
                            "(a [regions] name or a label), or a [prescription]")
        name = plan.prescription.structure
    return region_cells(world, None, region_label(name, plan.regions))


def run_mesh_transport(mesh: TetMesh, plan: Plan, settings: TransportSettings, *,
                       progress: bool | None = None) -> DoseResult:
    """Dose per tetrahedron of a mesh in vacuum (density from point_data ``density``).

    Tets are walked in Morton order (:func:`morton_order`); the result is in mesh order.
    """
    return simulate(World(mesh=mesh), plan, settings, progress=progress)


def run_voxel_transport(density: Image, plan: Plan, settings: TransportSettings, *,
                        labels: Image | None = None, progress: bool | None = None) -> DoseResult:
    """Dose per voxel on a density image [g/cm³] (constant density per voxel)."""
    return simulate(World(density=density, labels=labels), plan, settings, progress=progress)
