"""Doses of other codes back onto the breathing mesh, accumulated (``tetdose import-dose``).

One dose file per phase (:mod:`tetdose.coupling.dose_files`), each turned into a per-tet dose
D_{k,p} [Gy] on phase p's mesh by energy:

* a per-tet tally of energy E_{k,p} [MeV]: D_{k,p} = E_{k,p} · J_PER_MEV / (m_{k,p} / 1000),
  with m_{k,p} the tet's mass in tetdose (P1 density, :func:`tetdose.core.mass.tet_mass_g`);
* a per-tet tally of dose d_{k,p} [Gy] from a code that ran on the binned phase (``--exported``:
  the files ``tetdose export-phases`` wrote, whose density ρ^b_k gave that code the mass
  m^b_k = V_k ρ^b_k): the energy is d m^b and D_{k,p} = d_{k,p} m^b_k / m_{k,p}; without the
  export, m^b = m (the binning changes each tet's mass by ≤ the binning's mass error);
* a voxel dose D_v (EGSnrc ``.3ddose``, DICOM RT Dose, NRRD/MHA/NIfTI) on a grid containing
  the phase's mesh, computed on voxel densities ρ_v: by energy, E_k = Σ_v D_v ρ_v Vol(v ∩ k)
  over the voxel world's mass there, Σ_v ρ_v Vol(v ∩ k), with the exact overlaps
  (:func:`tetdose.coupling.onto_mesh.voxel_dose_onto_mesh`). ρ_v is the density the code ran
  on (``densities``) or, by default, the phase mesh voxelized mass-exactly on the dose grid
  (:func:`tetdose.core.voxelize.voxelize`, air outside). Voxel uncertainties σ_v
  (``.3ddose``) are independent between voxels, so with w_kv = ρ_v Vol(v ∩ k)
  σ_k = √(Σ_v (σ_v w_kv)²) / Σ_v w_kv.

Tally σ converts like the values. The phases are then accumulated on the mesh with
:func:`tetdose.dose.accumulate.accumulate_meshes`, D_k = Σ_p w_p D_{k,p} m_{k,p} / Σ_p w_p m_{k,p}
with the phases' time weights w_p, σ_k² = Σ_p w_p² (σ_{k,p} m_{k,p})² / (Σ_p w_p m_{k,p})², and
written as ``tetdose dose4d`` writes its mesh part (``phase_PPP.P.vtu``, ``accumulated.vtu`` with
cell_data dose, dose_std and mass_g, ``summary.json``), so ``tetdose compare`` reads them. When
every phase is a voxel dose, ``voxel/`` also holds the phase doses and their direct dose mapping
onto the first phase's grid (and, given ``densities``, the energy/mass transfer), as ``dose4d``.
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tetdose._atomic import atomic_write_dir
from tetdose._constants import G_PER_KG, J_PER_MEV, MM3_PER_CM3
from tetdose._typing import FloatArray
from tetdose.core.body import NEAR_MAX_SAID, near_max_gy
from tetdose.core.image import Image
from tetdose.core.io import write_image, write_mesh
from tetdose.core.mass import mass_g, tet_mass_g
from tetdose.core.mesh import TetMesh
from tetdose.core.overlap import Overlap
from tetdose.core.phase_names import order_by_names
from tetdose.core.voxelize import voxelize
from tetdose.coupling.dose_files import check_dose_values, dose_kind, read_voxel_dose
from tetdose.coupling.export import phase_stem
from tetdose.coupling.onto_mesh import mesh_overlap, voxel_dose_onto_mesh, voxel_share
from tetdose.coupling.tally_csv import read_tally_csv
from tetdose.dose.accumulate import (
    AccumulatedDose,
    accumulate_meshes,
    direct_dose_mapping,
    energy_mass_transfer,
)
from tetdose.dose.dose_to import check as check_dose_to
from tetdose.dose.dose_to import mark
from tetdose.errors import GeometryMismatchError, OptionError
from tetdose.motion.phases import PhaseSeries

#: A mesh vertex may lie this far [mm] outside the dose grid's outer voxel faces (round-off of
#: grids written with a few decimals).
COVER_TOL_MM = 1e-6
#: Default dose unit of imported doses (Monte Carlo codes score per source particle).
DEFAULT_UNIT = "Gy per source particle"


@dataclass(frozen=True, eq=False)
class PhaseDose:
    """Per-tet dose [Gy] and σ [Gy] of one phase, what it came from, and its voxel dose."""

    dose_gy: FloatArray
    dose_std_gy: FloatArray | None
    source: str
    kind: str
    voxel: Image | None = None
    voxel_density: Image | None = None


@dataclass(frozen=True, eq=False)
class ImportedDose4D:
    """The phases, their imported doses and the accumulation on the reference mesh."""

    series: PhaseSeries
    phases: list[PhaseDose]
    accumulated: AccumulatedDose
    unit: str = DEFAULT_UNIT
    dose_to: str = "medium"  # what the imported doses are, as the user states (dose.dose_to)

    def summary(self) -> dict[str, object]:
        mass = [tet_mass_g(self.series.mesh(k)) for k in range(self.series.n_phases)]
        cm3 = [self.series.mesh(k).volumes_mm3 / MM3_PER_CM3 for k in range(self.series.n_phases)]
        ref_cm3 = self.series.reference.volumes_mm3 / MM3_PER_CM3
        return {
            "imported": True,
            "phases": [{"phase_percent": float(self.series.phase_percent[k]),
                        "time_weight": float(self.series.time_weight[k]),
                        "source": p.source, "kind": p.kind,
                        "energy_j": float(np.dot(p.dose_gy, mass[k]) / G_PER_KG),  # in the mesh
                        "near_max_dose_gy": near_max_gy(p.dose_gy, cm3[k], mass[k] / cm3[k])}
                       for k, p in enumerate(self.phases)],
            "accumulated_near_max_dose_gy": near_max_gy(
                self.accumulated.dose_gy, ref_cm3, self.accumulated.mass_g / ref_cm3),
            "near_max": NEAR_MAX_SAID,
            "mass_spread_rel": self.accumulated.mass_spread_rel,
            "weights": self.accumulated.weights.tolist(),
            "units": {"dose": self.unit},
            "dose_to": self.dose_to,
        }


def check_covers(mesh: TetMesh, dose: Image, what: str) -> None:
    """Raise :class:`GeometryMismatchError` unless every vertex of ``mesh`` lies in the grid."""
    grid = dose.grid
    q = grid.to_grid_frame(mesh.points_mm)
    lo = -0.5 * grid.spacing_mm - COVER_TOL_MM
    hi = (np.asarray(grid.size) - 0.5) * grid.spacing_mm + COVER_TOL_MM
    out = np.any((q < lo) | (q > hi), axis=1)
    if out.any():
        lo_mm, hi_mm = mesh.bounds_mm()
        raise GeometryMismatchError(
            f"the dose grid of {what} does not cover the mesh: {int(out.sum())} of its "
            f"{mesh.n_points} vertices lie outside it (mesh spans {np.round(lo_mm, 1).tolist()} "
            f"to {np.round(hi_mm, 1).tolist()} mm); score the dose on a grid containing the "
            "whole mesh")


def voxel_std_on_mesh(mesh: TetMesh, std: Image, density: Image, overlap: Overlap
                      ) -> FloatArray:
    """σ_k = √(Σ_v (σ_v w_kv)²) / Σ_v w_kv [Gy] for independent voxel σ_v, with the weights
    w_kv = ρ_v Vol(v ∩ k) of :func:`~tetdose.coupling.onto_mesh.voxel_dose_onto_mesh`."""
    share = voxel_share(mesh, std.grid, overlap)
    w = share.multiply(np.asarray(density.array, dtype=np.float64).ravel()[None, :]).tocsr()
    s_v = np.asarray(std.array, dtype=np.float64).ravel()
    var = w.multiply(w).multiply((s_v**2)[None, :]).sum(axis=1).A1
    total = w.sum(axis=1).A1
    return np.divide(np.sqrt(var), total, out=np.zeros_like(total), where=total > 0)


def phase_dose(path: str | os.PathLike[str], mesh: TetMesh, *,
               density: Image | None = None,
               binned_density_g_cm3: FloatArray | None = None) -> PhaseDose:
    """The per-tet dose of one phase mesh (with point_data density) from one dose file."""
    path = Path(path)
    kind = dose_kind(path)
    if kind == "tally":
        tally = read_tally_csv(path, mesh.n_tets)
        mass = tet_mass_g(mesh)
        if tally.kind == "energy":
            scale = J_PER_MEV * G_PER_KG / mass
        elif binned_density_g_cm3 is None:
            scale = np.ones(mesh.n_tets)
        else:
            scale = mass_g(mesh.volumes_mm3, binned_density_g_cm3) / mass
        std = None if tally.sigma is None else tally.sigma * scale
        return PhaseDose(tally.value * scale, std, str(path), kind)
    dose, std = read_voxel_dose(path)
    check_dose_values(dose, str(path))
    check_covers(mesh, dose, str(path))
    overlap = mesh_overlap(mesh, dose.grid)
    if density is None:
        density = voxelize(mesh, mesh.point_data["density"], dose.grid, overlap=overlap)
    else:
        dose.grid.require_same(density.grid, f"the dose {path} and its density image")
    dose_k, _ = voxel_dose_onto_mesh(dose, density, mesh, overlap=overlap)
    std_k = None if std is None else voxel_std_on_mesh(mesh, std, density, overlap)
    return PhaseDose(dose_k, std_k, str(path), kind, dose, density)


def import_doses(series: PhaseSeries, paths: Sequence[str | os.PathLike[str]], *,
                 densities: Sequence[Image] | None = None,
                 binned_densities: Sequence[FloatArray] | None = None,
                 unit: str = DEFAULT_UNIT, dose_to: str = "medium") -> ImportedDose4D:
    """One dose file per phase of ``series`` → per-tet doses, accumulated; ``dose_to``: what
    the other code's doses are ("medium" or "water"), recorded.

    The files are paired with the phases by the phase numbers in their names where the names
    carry them (:func:`tetdose.core.phase_names.order_by_names`), else taken in phase order.
    """
    check_dose_to(dose_to)
    n = series.n_phases
    for what, items in (("dose files", paths), ("density images", densities),
                        ("exported phases", binned_densities)):
        if items is not None and len(items) != n:
            raise OptionError(f"{len(items)} {what} for {n} phases; give one per phase, in "
                              "phase order")
    paths = order_by_names(list(map(Path, paths)), series.phase_percent, "dose files")
    if series.density_g_cm3 is None:
        raise OptionError("the phases carry no density; run `tetdose deform` (the density "
                          "update) before importing doses onto them")
    meshes = [series.mesh(k) for k in range(n)]
    phases = [phase_dose(p, meshes[k], density=None if densities is None else densities[k],
                         binned_density_g_cm3=None if binned_densities is None
                         else binned_densities[k]) for k, p in enumerate(paths)]
    stds = [p.dose_std_gy for p in phases]
    acc = accumulate_meshes(meshes, [p.dose_gy for p in phases], weights=series.time_weight,
                            dose_std_gy=None if any(s is None for s in stds) else stds)
    return ImportedDose4D(series, phases, acc, unit, dose_to)


def write_imported(result: ImportedDose4D, out_dir: str | os.PathLike[str]) -> Path:
    """Write the phases and the accumulation as ``tetdose dose4d`` does (module docstring)."""
    series, acc = result.series, result.accumulated
    out = Path(out_dir)
    with atomic_write_dir(out) as tmp:
        for k, p in enumerate(result.phases):
            mesh = series.mesh(k)
            write_mesh(tmp / f"{phase_stem(float(series.phase_percent[k]))}.vtu",
                       mark(mesh.with_data(cell_data={
                           "dose": p.dose_gy, "mass_g": tet_mass_g(mesh),
                           "dose_std": np.zeros(mesh.n_tets) if p.dose_std_gy is None
                           else p.dose_std_gy}), result.dose_to))
        write_mesh(tmp / "accumulated.vtu", mark(series.reference.with_data(cell_data={
            "dose": acc.dose_gy, "mass_g": acc.mass_g,
            "dose_std": np.zeros_like(acc.dose_gy) if acc.dose_std_gy is None
            else acc.dose_std_gy}), result.dose_to))
        if all(p.voxel is not None for p in result.phases):
            _write_voxel_way(result, tmp / "voxel")
        (tmp / "summary.json").write_text(json.dumps(result.summary(), indent=2) + "\n")
    return out


def _write_voxel_way(result: ImportedDose4D, folder: Path) -> None:
    series = result.series
    doses = [p.voxel for p in result.phases]
    for k, dose in enumerate(doses):
        write_image(folder / f"{phase_stem(float(series.phase_percent[k]))}_dose.nrrd", dose)
    grid = doses[0].grid
    ref, pts, w = series.reference, series.points_mm, series.time_weight
    write_image(folder / "accumulated_direct_mapping.nrrd",
                direct_dose_mapping(ref, pts, doses, grid, weights=w))
    rho = [p.voxel_density for p in result.phases]
    if all(d.grid.same_as(grid) for d in doses):
        write_image(folder / "accumulated_energy_mass_transfer.nrrd",
                    energy_mass_transfer(ref, pts, doses, rho, grid, weights=w))
