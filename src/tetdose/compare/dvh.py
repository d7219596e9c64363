"""Cumulative dose–volume histograms from per-tetrahedron or per-voxel dose, and their metrics.

A structure is a set of elements i (tetrahedra or voxels) with dose d_i [Gy] and weight w_i
(volume [cm³] or mass [g]). The cumulative DVH is the weight fraction receiving at least D,

    V(D) = Σ_{d_i ≥ D} w_i / Σ_i w_i,

computed exactly from the sorted doses (no binning). D_x is the smallest dose received by the
hottest x % of the structure, D_x = min{d_i : Σ_{d_j ≥ d_i} w_j ≥ x/100 · W}, so for a uniform
dose every D_x equals that dose; V_D is V(D) in percent; Dmean = Σ w_i d_i / W (the
mass-weighted mean is the structure's energy / mass). ICRU Report 83 names D98/D50/D2 as
near-minimum/median/near-maximum doses.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from tetdose._constants import MM3_PER_CM3
from tetdose._typing import BoolArray, FloatArray
from tetdose.core.image import Image
from tetdose.core.mass import tet_mass_g
from tetdose.core.mesh import TetMesh
from tetdose.core.transfer import per_tet_dose, vertex_density
from tetdose.errors import DoseError, OptionError

WEIGHTS = ("volume", "mass")


@dataclass(frozen=True, eq=False)
class DVH:
    """A cumulative DVH: doses sorted descending and the cumulative weight fraction at each."""

    dose_gy: FloatArray  # (n,) descending
    cumulative_fraction: FloatArray  # (n,) Σ_{j ≤ i} w_j / W, increasing to 1
    total_weight: float  # W, in cm³ or g
    mean_gy: float
    weight: str
    name: str = ""

    def dose_at_percent(self, percent: float) -> float:
        """D_x [Gy]: minimum dose to the hottest ``percent`` % of the structure."""
        if not 0.0 <= percent <= 100.0:
            raise OptionError(f"D_x needs a percent in [0, 100], got {percent}; e.g. 95 for D95")
        if percent == 0.0:
            return float(self.dose_gy[0])
        i = np.searchsorted(self.cumulative_fraction, percent / 100.0 * (1 - 1e-12))
        return float(self.dose_gy[min(i, len(self.dose_gy) - 1)])

    def volume_at_dose_percent(self, dose_gy: float) -> float:
        """V_D [%]: weight fraction receiving at least ``dose_gy``."""
        n = np.searchsorted(-self.dose_gy, -dose_gy, side="right")  # elements with d ≥ dose
        return 100.0 * float(self.cumulative_fraction[n - 1]) if n else 0.0

    def curve(self, dose_levels_gy: FloatArray) -> FloatArray:
        """V(D) [%] at each dose level (for plotting)."""
        return np.array([self.volume_at_dose_percent(float(d)) for d in dose_levels_gy])

    def metrics(self, *, d_percent: Sequence[float] = (98, 95, 50, 2),
                v_gy: Sequence[float] = ()) -> dict[str, float]:
        """D98, D95, D50, D2, Dmean, Dmax, Dmin [Gy] and V_D [%] for each D in ``v_gy``."""
        out = {f"D{p:g}": self.dose_at_percent(p) for p in d_percent}
        out |= {"Dmean": self.mean_gy, "Dmax": float(self.dose_gy[0]),
                "Dmin": float(self.dose_gy[-1])}
        out |= {f"V{d:g}Gy": self.volume_at_dose_percent(d) for d in v_gy}
        return out


def dvh(dose_gy: FloatArray, weight: FloatArray, *, weight_kind: str = "volume", name: str = ""
        ) -> DVH:
    """The DVH of elements with doses ``dose_gy`` [Gy] and ``weight`` (volumes or masses)."""
    d = np.asarray(dose_gy, dtype=np.float64).ravel()
    w = np.asarray(weight, dtype=np.float64).ravel()
    if d.shape != w.shape:
        raise OptionError(f"{len(d)} doses for {len(w)} weights: give one weight per dose element")
    keep = w > 0
    d, w = d[keep], w[keep]
    if len(d) == 0:
        raise DoseError(f"structure {name!r} is empty (no element with positive weight): "
                        "check the structure's region label or mask")
    order = np.argsort(-d, kind="stable")
    d, w = d[order], w[order]
    total = float(w.sum())
    return DVH(d, np.cumsum(w) / total, total, float(np.dot(w, d) / total), weight_kind, name)


def mesh_dvh(mesh: TetMesh, dose_gy: FloatArray, *, region: int | None = None,
             weight: str = "volume", density_g_cm3: FloatArray | None = None, name: str = ""
             ) -> DVH:
    """DVH of a per-tet dose, over the tets of ``region`` (all if None), by volume or mass."""
    if weight not in WEIGHTS:
        raise OptionError(f"DVH weight must be one of {WEIGHTS}, got {weight!r}")
    w = (mesh.volumes_mm3 / MM3_PER_CM3 if weight == "volume"
         else tet_mass_g(mesh, vertex_density(mesh, density_g_cm3)))
    dose = per_tet_dose(mesh, dose_gy)
    if region is not None:
        if mesh.region is None:
            raise OptionError("the mesh has no region labels: pass region=None for the whole mesh")
        sel = mesh.region == region
        dose, w = dose[sel], w[sel]
    return dvh(dose, w, weight_kind=weight, name=name or _region_name(region))


def image_dvh(dose: Image, mask: BoolArray, *, density_g_cm3: Image | None = None,
              name: str = "") -> DVH:
    """DVH of a voxel dose inside ``mask``, by volume, or by mass with a density image."""
    sel = np.asarray(mask, dtype=bool)
    if sel.shape != dose.grid.shape:
        raise OptionError(f"mask shape {sel.shape} differs from the dose grid {dose.grid.shape}: "
                          "resample the mask onto the dose grid")
    v_cm3 = dose.grid.voxel_volume_mm3 / MM3_PER_CM3
    if density_g_cm3 is None:
        w, kind = np.full(int(sel.sum()), v_cm3), "volume"
    else:
        dose.grid.require_same(density_g_cm3.grid, "the dose and the density images")
        w, kind = np.asarray(density_g_cm3.array, dtype=np.float64)[sel] * v_cm3, "mass"
    return dvh(np.asarray(dose.array)[sel], w, weight_kind=kind, name=name)


def _region_name(region: int | None) -> str:
    return "all" if region is None else f"region {region}"
