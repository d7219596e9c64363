"""Prescriptions: scale doses per source photon to absolute Gy per fraction.

Transport reports dose per source photon (``Plan.particles`` = 1): every cell's dose is linear in
the number of source photons N, so one factor ``s = D_Rx / M(D)`` makes the prescription metric M
of the structure equal the prescribed dose per fraction D_Rx. M is volume (mass for doses on
tetrahedra or voxels: weights are the cells' mass) weighted:

- ``mean``: Σ m_i D_i / Σ m_i;
- ``D95`` / ``D50`` (``Dxx``): the dose received by at least xx % of the structure: the smallest
  dose D with Σ_{D_i ≥ D} m_i ≥ xx % of Σ m_i (a cumulative DVH read at xx %).

The same factor multiplies every output of one run (per phase and accumulated, mesh and voxel),
so relative comparisons are untouched; it is written into the run records
(``prescription_scale``: source photons per fraction). Without a prescription doses stay in
"Gy per source photon".
"""

from __future__ import annotations

import re
import warnings
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from tetdose._typing import FloatArray
from tetdose.errors import PlanError

#: A scaled maximum dose above this many times the prescription is warned about.
MAX_OVER_PRESCRIPTION = 5.0
#: The near-maximum checked against it: the dose exceeded by 0.1 % of the mass that scored (a
#: single tiny cell's statistical spike is not the maximum a physicist reads; ICRU 83 uses D2%).
NEAR_MAX = "D0.1"
#: Label of doses without a prescription (plots, files, records).
PER_PHOTON_UNIT = "Gy per source photon"
_KEYS = {"structure", "dose_gy", "metric", "fractions"}


@dataclass(frozen=True)
class Prescription:
    """``dose_gy`` per fraction to ``structure`` (a [regions] name or a label) by ``metric``."""

    structure: str
    dose_gy: float
    metric: str = "D95"
    fractions: int = 1

    def __post_init__(self) -> None:
        if not (np.isfinite(self.dose_gy) and self.dose_gy > 0):
            raise PlanError(f"[prescription] dose_gy must be positive, got {self.dose_gy}")
        if metric_percent(self.metric) is None and self.metric != "mean":
            raise PlanError(f"[prescription] metric {self.metric!r} is unknown; use D95, D50 "
                            "(any Dxx) or mean")
        if int(self.fractions) < 1:
            raise PlanError("[prescription] fractions must be at least 1")

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Prescription:
        unknown = set(d) - _KEYS
        if unknown or "structure" not in d or "dose_gy" not in d:
            raise PlanError(f"[prescription] needs structure and dose_gy (optional metric, "
                            f"fractions); unknown: {sorted(unknown)}")
        return cls(str(d["structure"]), float(d["dose_gy"]), str(d.get("metric", "D95")),
                   int(d.get("fractions", 1)))


def metric_percent(metric: str) -> float | None:
    """xx of ``"Dxx"`` (volume percent), else None."""
    m = re.fullmatch(r"D(\d+(?:\.\d+)?)", metric)
    if m is None or not 0.0 < float(m.group(1)) < 100.0:
        return None
    return float(m.group(1))


def dose_metric(dose_gy: FloatArray, weight: FloatArray, metric: str) -> float:
    """The prescription metric of doses ``dose_gy`` with cell weights (mass or volume)."""
    d, w = np.asarray(dose_gy, dtype=np.float64), np.asarray(weight, dtype=np.float64)
    if len(d) == 0 or w.sum() <= 0:
        raise PlanError("the prescription structure has no cells in this geometry")
    if metric == "mean":
        return float(np.dot(d, w) / w.sum())
    pct = metric_percent(metric)
    order = np.argsort(d)[::-1]  # highest dose first: cumulative volume receiving ≥ D
    cum = np.cumsum(w[order])
    k = int(np.searchsorted(cum, (pct or 0.0) / 100.0 * w.sum() * (1 - 1e-12)))
    return float(d[order][min(k, len(d) - 1)])


def region_label(name: str | int, regions: Mapping[str, int]) -> int:
    """Region label of a structure: a [regions] name, or an integer label as text."""
    if str(name) in regions:
        return int(regions[str(name)])
    try:
        return int(name)
    except ValueError:
        raise PlanError(f"structure {name!r} is not in [regions] ({sorted(regions)}); add "
                        f"[regions] {name} = LABEL to the plan") from None


def _parts(geometry: Any, labels: Any) -> tuple[Any, Any, int]:  # noqa: ANN401
    """(mesh or None, label image or None, number of voxel cells) of a TetMesh, a density Image
    (with ``labels``) or a transport world (duck-typed: ``mesh``, ``density``, ``labels``; its
    cells are the mesh's tetrahedra, then the grid's voxels)."""
    from tetdose.core.mesh import TetMesh

    if isinstance(geometry, TetMesh):
        return geometry, None, 0
    if hasattr(geometry, "mesh") and hasattr(geometry, "density"):
        n_vox = 0 if geometry.density is None else geometry.density.grid.n_voxels
        return geometry.mesh, geometry.labels, n_vox
    return None, labels, geometry.grid.n_voxels


def region_cells(geometry: Any, labels: Any, label: int) -> np.ndarray:  # noqa: ANN401
    """Boolean mask of the cells of region ``label``: tets of a mesh (cell_data ``region``),
    voxels of a label image (beside a density image), or both in a world (tets first)."""
    mesh, lab, n_vox = _parts(geometry, labels)
    masks = []
    if mesh is not None:
        if mesh.region is None:
            raise PlanError("the mesh has no region labels; structures need cell_data region")
        masks.append(np.asarray(mesh.region) == label)
    if n_vox:
        if lab is None and mesh is None:
            raise PlanError("a structure on a CT needs a label image (tetdose dose --labels)")
        masks.append(np.zeros(n_vox, dtype=bool) if lab is None
                     else np.asarray(lab.array).reshape(-1) == label)
    mask = np.concatenate(masks)
    if not mask.any():
        raise PlanError(f"region label {label} has no cells in this geometry")
    return mask


def region_centroid_mm(geometry: Any, labels: Any, label: int) -> FloatArray:  # noqa: ANN401
    """Volume-weighted centroid [mm] of region ``label``: its tetrahedra if the geometry has a
    mesh holding it, else its voxel centres in the label image."""
    mesh, lab, _ = _parts(geometry, labels)
    if mesh is not None and mesh.region is not None and np.any(mesh.region == label):
        sel = np.asarray(mesh.region) == label
        return np.average(mesh.centroids_mm[sel], axis=0, weights=mesh.volumes_mm3[sel])
    if lab is None:
        region_cells(geometry, labels, label)  # raises the reason
        raise PlanError(f"region label {label} is not in the mesh")
    idx = np.argwhere(np.asarray(lab.array) == label)[:, ::-1]  # (k, j, i) → (i, j, k)
    if len(idx) == 0:
        raise PlanError(f"region label {label} has no cells in this geometry")
    return lab.grid.index_to_physical(idx.astype(np.float64)).mean(axis=0)


def scale_for(rx: Prescription, dose_gy: FloatArray, mass_g: FloatArray,
              mask: np.ndarray) -> float:
    """Source photons per fraction: ``rx.dose_gy / metric(dose in the structure)``.

    Refused when the metric is 0: if part of the structure scored nothing it is the statistics
    ("too few histories: N % of the structure scored nothing"), if all of it, the beams miss it
    or too few histories reach it. Warns when the scaled near-maximum dose (:data:`NEAR_MAX`) exceeds
    :data:`MAX_OVER_PRESCRIPTION` × the prescription (a noisy metric inflates every dose).
    """
    d, w = np.asarray(dose_gy, dtype=np.float64)[mask], np.asarray(mass_g, dtype=np.float64)[mask]
    m = dose_metric(d, w, rx.metric)
    total = float(w.sum())
    zero = float(w[d <= 0.0].sum()) / total if total > 0 else 1.0
    if m <= 0.0:
        if zero >= 1.0:
            raise PlanError(f"the structure {rx.structure!r} scored no dose at all: the beams "
                            "miss it, or too few histories reach it; check the beams' aim, or "
                            "raise --histories")
        raise PlanError(f"too few histories: {_percent(zero)} % of the structure "
                        f"{rx.structure!r} scored nothing, so its {rx.metric} is 0 (raise "
                        "--histories; if that stays, the beams cover only part of it)")
    scale = rx.dose_gy / m
    all_d, all_w = np.asarray(dose_gy, dtype=np.float64), np.asarray(mass_g, dtype=np.float64)
    scored = (all_d > 0.0) & (all_w > 0.0)
    peak = dose_metric(all_d[scored], all_w[scored], NEAR_MAX) * scale if scored.any() else 0.0
    if peak > MAX_OVER_PRESCRIPTION * rx.dose_gy:
        why = (f"{_percent(zero)} % of the structure scored nothing: too few histories (raise "
               "--histories)" if zero > 0 else "the prescription metric may rest on too few "
               "histories (raise --histories), or check the structure and metric")
        warnings.warn(f"prescribed {rx.metric} = {rx.dose_gy:g} Gy per fraction to "
                      f"{rx.structure!r} puts the near-maximum dose ({NEAR_MAX}) at {peak:.4g} "
                      "Gy per fraction, "
                      f"{peak / rx.dose_gy:.0f}× the prescription; {why}", stacklevel=2)
    return scale


def _percent(fraction: float) -> str:
    """A percentage that never reads 0 or 100 when it is not."""
    pct = 100.0 * fraction
    if 1.0 <= pct <= 99.0:
        return f"{pct:.0f}"
    return f"{pct:.2g}" if pct < 1.0 else f"{min(pct, 99.99):.4g}"


def record(rx: Prescription, scale: float) -> dict[str, Any]:
    """What a run record says about the prescription."""
    return {"prescription": {"structure": rx.structure, "dose_gy_per_fraction": rx.dose_gy,
                             "metric": rx.metric, "fractions": rx.fractions,
                             "total_dose_gy": rx.dose_gy * rx.fractions},
            "prescription_scale": scale, "units": {"dose": "Gy per fraction"}}
