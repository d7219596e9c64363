"""A mesh dose compared with a voxel dose: the workflow of ``tetdose compare`` and the demo study.

The mesh dose is put on the voxel dose's grid (:func:`tetdose.core.transfer.mesh_dose_to_grid`:
energy-conserving, mass-weighted with the mesh's point_data ``density`` when present). The mesh
dose exists only inside the mesh (an organ mesh in a hybrid run covers a few organs), so gamma
is evaluated where both doses are defined — the voxels at least half inside the mesh
(:func:`half_inside`) — with the reference maximum taken there too. Then: gamma maps for each
criterion of :data:`CRITERIA` (on a seeded sample of at most ``gamma_max_points`` points, and on
the axial slice through the reference maximum for the figure), DVHs per structure (a tet belongs
to a structure when the voxel holding its centroid does, :meth:`ImageGrid.voxel_of`; the whole
mesh's voxel DVH covers the compared region), profiles through the maximum along x, y and z,
and the mean absolute difference above the threshold.

**Regions.** A mesh DVH and a voxel DVH of "the same" structure cover different matter: the
tetrahedra follow the organ's surface, the voxels are those of the mask (or at least half inside
the mesh). For each structure the summary gives both regions' volume [cm³] and mass [g] (mesh:
eq. 3 tet masses from the vertex densities; voxels: ρ_j V from ``density`` — the CT through the
calibration — or, without it, the mesh's mass per covered volume in each voxel, said so), both
means — volume-weighted Σ V_i D_i / Σ V_i and mass-weighted Σ m_i D_i / Σ m_i (energy / mass) —
and the mesh dose put on the voxels (energy-conserving transfer) averaged over the *voxel*
region: the mesh and voxel means on the same voxels. When the DVH means differ by more than
:data:`REGION_NOTE_PERCENT` and the regions do too, a note says how much of the difference the
regions explain.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from tetdose._constants import MM3_PER_CM3
from tetdose._typing import BoolArray, FloatArray, IntArray
from tetdose.compare import report
from tetdose.compare.consistency import (
    compared_region,
    expected_gamma_pass,
    mesh_std_to_grid,
    pair_significance,
)
from tetdose.compare.dvh_bands import banded_dvh, compare_points
from tetdose.compare.gamma import gamma_index
from tetdose.compare.profiles import image_profile, mesh_profile
from tetdose.core.body import NEAR_MAX_CM3, TISSUE_FLOOR_G_CM3, near_max_gy
from tetdose.core.image import Image, ImageGrid
from tetdose.core.mass import tet_mass_g
from tetdose.core.mesh import TetMesh
from tetdose.core.overlap import Overlap, compute_overlap
from tetdose.core.transfer import mesh_dose_to_grid, mesh_mass_on_grid, per_tet_dose
from tetdose.errors import GeometryMismatchError, MeshError, OptionError
from tetdose.plan.prescription import PER_PHOTON_UNIT

#: Gamma criteria of the comparison: (dose %, DTA mm, local).
CRITERIA = ((3.0, 3.0, False), (2.0, 2.0, False), (3.0, 3.0, True))
#: A voxel is compared when at least this fraction of its volume lies inside the mesh.
REGION_FRACTION = 0.5
#: What the near-maximum of the summary is.
NEAR_MAX_SAID = (f"D{NEAR_MAX_CM3:g}cm³ over the compared region (in tissue: density ≥ "
                 f"{TISSUE_FLOOR_G_CM3:g} g/cm³ when known), never one voxel in air")
#: How the systematic part is separated from the statistical one.
SIGNIFICANCE_SAID = ("per structure: mean relative difference (first dose to the reference, "
                     "mass-weighted) ± 1σ; systematic part: maximum-likelihood mixture of "
                     "statistical noise and a fraction f of points shifted by δ (after Kawrakow "
                     "& Fippel, PMB 45:2163, 2000; tetdose.compare.significance)")
#: Mean doses (or regions) differing by more than this [%] get an explaining note.
REGION_NOTE_PERCENT = 1.0


@dataclass(frozen=True, eq=False)
class Comparison:
    """The report of one comparison: figures, the summary table, the mesh dose on the voxel
    grid [unit of the doses] and the compared region (voxels ≥ half inside the mesh)."""

    figures: list[report.Figure]
    summary: dict[str, Any]
    mesh_on_grid: Image
    region: BoolArray

    def write(self, out_dir: str | Path) -> Path:
        """The HTML + JSON report folder (:func:`tetdose.compare.report.write_report`)."""
        return report.write_report(out_dir, self.figures, self.summary)


def half_inside(overlap: Overlap) -> BoolArray:
    """Voxels of the overlap's grid at least :data:`REGION_FRACTION` inside its mesh (numpy
    shape of the grid)."""
    grid = overlap.grid
    cover = overlap.covered_volume_per_voxel_mm3()
    return (cover >= REGION_FRACTION * grid.voxel_volume_mm3).reshape(grid.shape)


def labels_on(labels: Image, grid: ImageGrid) -> IntArray:
    """Label image sampled at ``grid``'s voxel centres (the voxel holding each, 0 off it)."""
    if labels.grid.same_as(grid):
        return np.asarray(labels.array).astype(np.int64)
    voxel = labels.grid.voxel_of(grid.voxel_centers_mm())
    out = np.asarray(labels.array).ravel()[np.maximum(voxel, 0)].astype(np.int64)
    return np.where(voxel >= 0, out, 0).reshape(grid.shape)


def read_structure_masks(path: str | Path, grid: ImageGrid) -> dict[str, BoolArray]:
    """Name → voxel mask on ``grid``: RTSTRUCT ROIs by name, or ``label N`` per image label."""
    from tetdose.core.io import read_labels
    from tetdose.dicom.rtstruct import is_rtstruct, read_rtstruct, structure_masks

    if is_rtstruct(path):
        return structure_masks(read_rtstruct(path), grid, skip_unusable=True)
    labels = labels_on(read_labels(path, f"the structures' label image {path}"), grid)
    return {f"label {lab}": labels == lab for lab in np.unique(labels[labels > 0])}


def read_mesh_dose(path: str | Path) -> tuple[TetMesh, FloatArray]:
    """A dose VTU (cell_data ``dose``) → (mesh, per-tet dose)."""
    from tetdose.core.io import read_mesh

    mesh = read_mesh(path)
    if "dose" not in mesh.cell_data:
        raise MeshError(f"{path} has no cell_data 'dose'; give a dose VTU from `tetdose dose`")
    return mesh, np.asarray(mesh.cell_data["dose"], dtype=np.float64).reshape(-1)


def recorded_dose_unit(dose_path: str | Path) -> str:
    """The dose unit a run record beside ``dose_path`` states (``<stem>.json`` of ``tetdose
    dose``, ``summary.json`` of ``tetdose dose4d``): "Gy per fraction" when prescribed, else
    (no prescription, or no record) :data:`~tetdose.plan.prescription.PER_PHOTON_UNIT`."""
    path = Path(dose_path)
    for record in (path.with_name(path.name.split(".")[0] + ".json"),
                   path.with_name("summary.json")):
        try:
            units = json.loads(record.read_text(encoding="utf-8")).get("units", {})
        except (OSError, ValueError, AttributeError):
            continue
        if isinstance(units, dict) and isinstance(units.get("dose"), str):
            return units["dose"]
    return PER_PHOTON_UNIT


def compare_doses(mesh: TetMesh, mesh_dose: FloatArray, voxel_dose: Image, *,
                  structures: Mapping[str, BoolArray] | None = None, reference: str = "voxel",
                  threshold_percent: float = 10.0, gamma_max_points: int | None = 200_000,
                  criteria: tuple[tuple[float, float, bool], ...] = CRITERIA,
                  unit: str = PER_PHOTON_UNIT, density: Image | None = None,
                  mesh_std: FloatArray | None = None, voxel_std: Image | None = None,
                  body: BoolArray | None = None) -> Comparison:
    """Compare a per-tet dose with a voxel dose (module docstring); doses in ``unit``.

    ``structures``: name → voxel mask on the voxel dose's grid (DVHs per structure besides the
    whole mesh); ``reference``: "voxel" or "mesh", the gamma reference; ``density``: voxel
    densities [g/cm³] on the voxel dose's grid (the CT through its calibration) for the voxel
    regions' masses and the tissue floor (default: estimated from the mesh's densities);
    ``mesh_std``/``voxel_std``: each dose's σ (None: compared as exact);
    ``body``: the body outline on the voxel grid (:mod:`tetdose.compare.consistency`).
    """
    if reference not in ("voxel", "mesh"):
        raise OptionError(f"the gamma reference must be 'voxel' or 'mesh', got {reference!r}")
    dose = per_tet_dose(mesh, mesh_dose)
    voxel = voxel_dose.with_array(np.asarray(voxel_dose.array, dtype=np.float64))
    for name, other in (("density (--ct)", density), ("σ image", voxel_std)):
        if other is not None:
            voxel.grid.require_same(other.grid, f"the voxel dose and its {name}")
    overlap = compute_overlap(mesh, voxel.grid)
    mesh_img = mesh_dose_to_grid(mesh, dose, voxel.grid, overlap=overlap)
    regions = _Regions(mesh, voxel.grid, overlap, density)
    region, region_said = compared_region(half_inside(overlap), body, regions.voxel_rho)
    if not region.any():
        raise GeometryMismatchError("no voxel of the dose grid lies at least half inside the "
                                    "mesh (and in the body's tissue); compare a mesh dose with a "
                                    "voxel dose of the same patient")
    sig = _Sigmas(mesh, mesh_std, voxel_std, voxel.grid, overlap)
    ref, ev = (voxel, mesh_img) if reference == "voxel" else (mesh_img, voxel)
    s_ref, s_ev = (sig.voxel, sig.mesh) if reference == "voxel" else (sig.mesh, sig.voxel)
    cm3 = voxel.grid.voxel_volume_mm3 / MM3_PER_CM3
    norm = near_max_gy(np.where(region, ref.array, 0.0), cm3)
    k, centre_index = _hot_slice(ref.array, region, norm)
    figures = [report.dose_slices_figure(mesh_img, voxel, k=k, unit=unit, mesh=mesh,
                                         region=region)]
    labels = ("mesh", "voxel") if reference == "voxel" else ("voxel", "mesh")
    above = region & (ref.array >= threshold_percent / 100.0 * norm)
    # without σ there is no Δ/σ to map (the summary says: compared as exact)
    table, noise_figures = pair_significance(
        ref, s_ref, ev, s_ev, region, structures or {}, threshold_percent / 100.0 * norm,
        regions.voxel_weight(), k=k if sig.any else None, labels=labels, unit=unit)
    figures += noise_figures
    gammas = _gammas(ref, ev, (s_ref, s_ev) if sig.any else None, region, k, norm, criteria,
                     threshold_percent, gamma_max_points, figures)
    dvh_summary = _dvhs(mesh, dose, mesh_img, voxel, {"mesh": region, **(structures or {})},
                        unit, figures, regions, sig)
    centre = voxel.grid.index_to_physical(np.array(centre_index[::-1], dtype=float))
    lo_mm, hi_mm = mesh.bounds_mm()
    for axis, name in enumerate("xyz"):
        a, b = centre.copy(), centre.copy()
        a[axis], b[axis] = lo_mm[axis], hi_mm[axis]
        figures.append(report.profiles_figure(
            [mesh_profile(mesh, dose, a, b), image_profile(voxel, a, b)], name=f"profile_{name}",
            unit=unit))
    diff = (mesh_img.array - voxel.array)[above]
    n_region = int(region.sum())
    near = {f"{n}_dose_near_max_gy": near_max_gy(np.where(region, img.array, 0.0), cm3)
            for n, img in (("mesh", mesh_img), ("voxel", voxel))}
    summary = {"unit": unit,
               "region": {"description": region_said, "voxels": n_region,
                          "volume_cm3": n_region * cm3,
                          "reference_near_max_gy": norm, "near_max": NEAR_MAX_SAID},
               **near,
               "uncertainty": sig.said, "significance_method": SIGNIFICANCE_SAID,
               "mean_abs_difference_gy": float(np.abs(diff).mean()) if diff.size else float("nan"),
               "structures": table, "gamma": gammas, "dvh": dvh_summary}
    return Comparison(figures, summary, mesh_img, region)


def _hot_slice(ref: FloatArray, region: BoolArray, near_max: float) -> tuple[int, tuple[int, ...]]:
    """The axial slice and voxel index of the centroid of the region's voxels at or above
    95 % of the near-maximum (the hottest tissue, not one noisy voxel)."""
    hot = np.argwhere(region & (ref >= 0.95 * near_max))
    if len(hot) == 0:
        hot = np.argwhere(region)
    c = tuple(int(round(x)) for x in hot.mean(axis=0))
    return c[0], c


class _Sigmas:
    """Both doses' σ on the voxel grid (zeros for a dose without σ) and what the report says."""

    def __init__(self, mesh: TetMesh, mesh_std: FloatArray | None, voxel_std: Image | None,
                 grid: ImageGrid, overlap: Overlap) -> None:
        zeros = np.zeros(grid.shape)
        self.mesh = zeros if mesh_std is None else mesh_std_to_grid(
            mesh, mesh_std, grid, overlap).array
        self.voxel = zeros if voxel_std is None else np.asarray(voxel_std.array, np.float64)
        self.tet = None if mesh_std is None else np.asarray(mesh_std, np.float64).ravel()
        self.any = mesh_std is not None or voxel_std is not None
        self.said = {"mesh": "σ from the mesh's dose_std (batches), put on the voxels"
                     if mesh_std is not None else "no σ given: compared as exact",
                     "voxel": "σ from the dose's _std image (batches)" if voxel_std is not None
                     else "no σ given: compared as exact"}



def _gammas(ref: Image, ev: Image, sigmas: tuple[FloatArray, FloatArray] | None,
            region: BoolArray, k: int, norm: float,
            criteria: tuple[tuple[float, float, bool], ...], threshold_percent: float,
            max_points: int | None, figures: list[report.Figure]) -> dict[str, Any]:
    """Gamma summaries per criterion (sampled over the region), with the pass rate two unbiased
    runs of these σ would reach (:func:`~tetdose.compare.consistency.expected_gamma_pass`), and
    a figure of slice k each."""
    gammas = {}
    for dd, dta, local in criteria:
        kw = {"dose_percent": dd, "dta_mm": dta, "local": local,
              "threshold_percent": threshold_percent, "mask": region, "normalization_gy": norm}
        g = gamma_index(ref, ev, max_points=max_points, **kw)
        row = g.summary()
        if sigmas is not None:
            row |= expected_gamma_pass(ref, sigmas[0], ev, sigmas[1], **kw)
        else:
            row["expected_pass_rate_percent"] = 100.0  # exact doses: no noise to fail
        gammas[row["criterion"]] = row
        slice_mask = np.zeros_like(region)
        slice_mask[k] = region[k]
        g_slice = gamma_index(ref, ev, **(kw | {"mask": slice_mask}))
        figures.append(report.gamma_figure(g_slice, k=k,
                                           expected=row["expected_pass_rate_percent"]))
    return gammas


class _Regions:
    """Volumes, masses and weights of the tets and voxels a DVH covers (module docstring)."""

    def __init__(self, mesh: TetMesh, grid: ImageGrid, overlap: Overlap,
                 density: Image | None) -> None:
        self.tet_volume_cm3 = mesh.volumes_mm3 / MM3_PER_CM3
        self.tet_mass_g = (tet_mass_g(mesh) if "density" in mesh.point_data else None)
        self.voxel_cm3 = grid.voxel_volume_mm3 / MM3_PER_CM3
        self.voxel_shape = grid.shape
        if density is not None:
            self.voxel_rho = np.asarray(density.array, dtype=np.float64)
            self.mass_source = "voxel masses from the CT's densities (--ct)"
        elif self.tet_mass_g is not None:
            mass = mesh_mass_on_grid(mesh, grid, overlap=overlap).array
            cover_cm3 = overlap.covered_volume_per_voxel_mm3().reshape(grid.shape) / MM3_PER_CM3
            self.voxel_rho = np.divide(mass, cover_cm3, out=np.full(grid.shape, np.nan),
                                       where=cover_cm3 > 0)
            self.mass_source = ("voxel masses estimated from the mesh's densities (no --ct; "
                                "voxels outside the mesh have none)")
        else:
            self.voxel_rho = None
            self.mass_source = "no densities: masses unknown"

    def voxel_weight(self) -> FloatArray:
        """Each voxel's mass [g] where its density is known, else its volume [cm³]: the weights
        of the mean relative difference."""
        vol = np.full(self.voxel_shape, self.voxel_cm3)
        if self.voxel_rho is None:
            return vol
        rho = self.voxel_rho
        return np.where(np.isfinite(rho), np.nan_to_num(rho) * self.voxel_cm3, vol)

    def mesh_part(self, sel: BoolArray, dose: FloatArray) -> dict[str, Any]:
        out = {"volume_cm3": float(self.tet_volume_cm3[sel].sum())}
        if self.tet_mass_g is not None:
            m = self.tet_mass_g[sel]
            out |= {"mass_g": float(m.sum()), "Dmean_mass_weighted": _mean(dose[sel], m)}
        return out

    def voxel_part(self, mask: BoolArray, dose: FloatArray) -> dict[str, Any]:
        out: dict[str, Any] = {"volume_cm3": float(mask.sum()) * self.voxel_cm3}
        if self.voxel_rho is not None:
            rho = self.voxel_rho[mask]
            known = np.isfinite(rho)
            if known.any():
                m = rho[known] * self.voxel_cm3
                out |= {"mass_g": float(m.sum()),
                        "Dmean_mass_weighted": _mean(dose[mask][known], m)}
            if not known.all():
                out["voxels_without_density"] = int((~known).sum())
        return out


def _mean(d: FloatArray, w: FloatArray) -> float:
    total = float(np.sum(w))
    return float(np.dot(d, w) / total) if total > 0 else float("nan")


def _dvhs(mesh: TetMesh, dose: FloatArray, mesh_img: Image, voxel: Image,
          masks: Mapping[str, BoolArray], unit: str, figures: list[report.Figure],
          regions: _Regions, sig: _Sigmas) -> dict[str, Any]:
    """Mesh (by tet volume) and voxel DVHs of the whole mesh (its tets; the compared voxels) and
    of each structure, with each region's volume, mass and means (module docstring), each DVH
    point with its σ and the differences flagged that exceed their combined uncertainty
    (:mod:`tetdose.compare.dvh_bands`)."""
    structures = {}
    tet_voxel = voxel.grid.voxel_of(mesh.centroids_mm)
    for name, mask in masks.items():
        mask = np.asarray(mask, dtype=bool)
        if name == "mesh" and not structures:
            sel = np.ones(mesh.n_tets, bool)
        else:
            sel = (tet_voxel >= 0) & mask.ravel()[np.maximum(tet_voxel, 0)]
            name = name if name != "mesh" else "structure mesh"
        structures[name] = (sel, mask)
    curves, table = {}, {}
    v_cm3 = voxel.grid.voxel_volume_mm3 / MM3_PER_CM3
    for name, (sel, mask) in structures.items():
        if not sel.any() or not mask.any():
            continue
        hm = banded_dvh(dose[sel], None if sig.tet is None else sig.tet[sel],
                        mesh.volumes_mm3[sel] / MM3_PER_CM3, name="mesh")  # by volume
        hv = banded_dvh(np.asarray(voxel.array)[mask], sig.voxel[mask],
                        np.full(int(mask.sum()), v_cm3), name="voxel")
        curves[name] = [hm, hv]
        mesh_side = hm.metrics() | regions.mesh_part(sel, dose)
        voxel_side = hv.metrics() | regions.voxel_part(mask, np.asarray(voxel.array))
        same = {"mesh_Dmean": float(np.asarray(mesh_img.array)[mask].mean()),
                "voxel_Dmean": hv.dvh.mean_gy}
        table[name] = {"mesh": mesh_side, "voxel": voxel_side, "same_voxels": same,
                       "points": compare_points(hm, hv), "mass_source": regions.mass_source}
        note = _region_note(mesh_side, voxel_side, same)
        if note:
            table[name]["note"] = note
    figures.append(report.dvh_figure(curves, unit=unit))
    return table


def _pct(a: float, b: float) -> float:
    return 100.0 * (a - b) / b if b else float("nan")


def _region_note(mesh: dict[str, Any], voxel: dict[str, Any], same: dict[str, float]
                 ) -> str | None:
    """Why the two DVH means differ, when the regions do (module docstring)."""
    total = _pct(mesh["Dmean"], voxel["Dmean"])
    dv = _pct(mesh["volume_cm3"], voxel["volume_cm3"])
    dm = _pct(mesh["mass_g"], voxel["mass_g"]) if "mass_g" in mesh and "mass_g" in voxel \
        else float("nan")
    if not (abs(total) > REGION_NOTE_PERCENT and (abs(dv) > REGION_NOTE_PERCENT
                                                  or abs(dm) > REGION_NOTE_PERCENT)):
        return None
    on_same = _pct(same["mesh_Dmean"], same["voxel_Dmean"])
    mass = (f"{mesh['mass_g']:.4g} g in {mesh['volume_cm3']:.4g} cm³ of tetrahedra vs "
            f"{voxel['mass_g']:.4g} g in {voxel['volume_cm3']:.4g} cm³ of voxels"
            if np.isfinite(dm) else f"{mesh['volume_cm3']:.4g} cm³ of tetrahedra vs "
            f"{voxel['volume_cm3']:.4g} cm³ of voxels")
    return (f"the mean doses differ by {total:+.1f} % but the DVHs cover different matter "
            f"({mass}); on the same voxels the mesh dose differs by {on_same:+.1f} %, so "
            f"{total - on_same:+.1f} points of the difference come from the regions, not the "
            "doses")
