"""Volume sources → the flat arrays the kernel samples (:mod:`tetdose.transport.sources._volume`).

Each source's cells are those of its region (mesh ``region`` labels and the label image; every
cell of the world without a region) with a positive mass; a cell is drawn by its mass (kernel
cell order: tets in Morton order, then voxels), so particles are born uniformly per unit mass.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from tetdose._typing import FloatArray, IntArray
from tetdose.errors import PlanError
from tetdose.plan.volume_source import VolumeSource
from tetdose.transport.geometry.world import World, WorldArrays, mesh_density
from tetdose.transport.sources._volume import VolumeArrays

#: Kernel species code of each particle name (0 e⁻, 1 e⁺, 2 photon).
SPECIES = {"electron": 0, "positron": 1, "photon": 2}


def empty_volume_arrays() -> VolumeArrays:
    """No volume source (the kernels' types, zero rows)."""
    i0, f0 = np.zeros(0, np.intp), np.zeros(0)
    one = np.zeros(1, np.intp)
    return VolumeArrays(f0, i0, one, f0, f0, one.copy(), i0.copy(), f0.copy(),
                        np.zeros((0, 4), np.intp), np.zeros((0, 3)), f0.copy())


def _cell_regions(world: World, order: IntArray | None) -> IntArray | None:
    """Region label per kernel cell (tets in kernel order, then voxels); None without labels."""
    mesh = world.mesh
    parts, labelled = [], False
    none = np.iinfo(np.int64).min
    if mesh is not None:
        labelled |= mesh.region is not None
        reg = (np.full(mesh.n_tets, none, np.int64) if mesh.region is None
               else np.asarray(mesh.region, np.int64))
        parts.append(reg[order] if order is not None else reg)
    if world.grid is not None:
        labelled |= world.labels is not None
        parts.append(np.full(world.grid.n_voxels, none, np.int64) if world.labels is None
                     else np.asarray(world.labels.array).reshape(-1).astype(np.int64))
    return np.concatenate(parts) if labelled else None


def volume_arrays(volumes: Sequence[VolumeSource], world: World, arrays: WorldArrays,
                  to_frame: Callable[[FloatArray], FloatArray] | None = None) -> VolumeArrays:
    """Flatten ``volumes`` for ``world`` (``arrays`` its kernel arrays; ``to_frame`` maps mesh
    points into the world's frame). PlanError if a region is missing or has no mass."""
    if not volumes:
        return empty_volume_arrays()
    mesh = world.mesh
    m_tets = 0 if mesh is None else mesh.n_tets
    order = arrays.order
    mass = arrays.mass_g.copy()
    if mesh is not None and order is not None:
        mass[:m_tets] = arrays.mass_g[:m_tets][order]
    regions = _cell_regions(world, order)
    cells, cdfs = [], []
    for v in volumes:
        if v.region is None:
            chosen = mass > 0.0
        elif regions is None:
            raise PlanError(f"a volume source names region {v.region}, but the world has no "
                            "region labels (mesh region / label image); drop region = … to fill "
                            "the whole world")
        else:
            chosen = (regions == v.region) & (mass > 0.0)
        ids = np.flatnonzero(chosen)
        if ids.size == 0:
            where = "the world" if v.region is None else f"region {v.region}"
            raise PlanError(f"a volume source fills {where}, which has no mass; check the "
                            "region label and the densities")
        c = np.cumsum(mass[ids])
        cells.append(ids.astype(np.intp))
        cdfs.append(c / c[-1])
    w = np.array([v.weight for v in volumes], dtype=np.float64)
    lines = [np.asarray(v.line_weights) / np.sum(v.line_weights) for v in volumes]
    if mesh is not None:
        pts = mesh.points_mm if to_frame is None else to_frame(mesh.points_mm)
        tets = mesh.tets[order] if order is not None else mesh.tets
        rho = mesh_density(mesh)
    else:
        pts, tets, rho = np.zeros((0, 3)), np.zeros((0, 4), np.intp), np.zeros(0)
    offsets = lambda parts: np.concatenate(  # noqa: E731
        [[0], np.cumsum([len(p) for p in parts])]).astype(np.intp)
    c_ = np.ascontiguousarray
    return VolumeArrays(
        src_cdf=np.cumsum(w) / w.sum(),
        particle=np.array([SPECIES[v.particle] for v in volumes], dtype=np.intp),
        spec_start=offsets(lines),
        spec_energy=np.concatenate([v.energies_mev for v in volumes]).astype(np.float64),
        spec_cdf=np.concatenate([np.cumsum(x) for x in lines]).astype(np.float64),
        cell_start=offsets(cells), cell=np.concatenate(cells),
        cell_cdf=np.concatenate(cdfs).astype(np.float64),
        tets=c_(tets, dtype=np.intp), points=c_(pts, dtype=np.float64),
        point_density=c_(rho, dtype=np.float64))
