"""One material per tetrahedron for codes that take a constant density per element.

Codes that track on tetrahedra (Geant4 ``G4Tet``, PHITS, MCNP6 unstructured mesh) give every
element one material with one density; tetdose's density is linear in each tet. The density
that keeps each tet's mass is its mean over the tet,

    ρ̄_k = m_k / V_k = ¼ Σ_a ρ_a          (the paper's eq. 3, exact for ρ linear in the tet)

Too many materials slow those codes down, so the tets are binned. Each tet first gets its
*composition class* — the material of its region in the plan's ``[materials]`` table, else its
density class (:func:`tetdose.transport.physics.materials.material_for_density`: air, lung,
adipose, soft tissue, bone), the rule tetdose's own transport uses — and within a class the
tets are grouped by density. A group b gets the density that keeps its mass,

    ρ_b = Σ_{k∈b} m_k / Σ_{k∈b} V_k,

so the total mass changes only by the rounding of ρ_b to :data:`DENSITY_DIGITS` significant
digits, and each tet's mass by V_k (ρ_b − ρ̄_k). The binning reports

    mass error  ε = Σ_k V_k |ρ_b(k) − ρ̄_k| / Σ_k m_k      (what no per-tet dose can undo)
    total change  Δ = (Σ_k V_k ρ_b(k) − Σ_k m_k) / Σ_k m_k.

Groups are made by greedy splitting: start with one group per class; repeatedly split the group
with the largest Σ V |ρ − ρ_b| at the point (between two distinct sorted densities) that
minimises the two halves' sum, until ``n_bins`` materials exist or, by default, until
ε ≤ :data:`DEFAULT_MAX_MASS_ERROR` (0.1 %). Each split costs O(n log n) in the group's size.
"""

from __future__ import annotations

import heapq
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from tetdose._constants import MM3_PER_CM3
from tetdose._typing import FloatArray, IntArray
from tetdose.core.mass import tet_mass_g
from tetdose.core.mesh import TetMesh
from tetdose.errors import DensityError, OptionError, PlanError
from tetdose.transport.physics.materials import (
    DENSITY_CLASS_MATERIALS,
    MATERIALS,
    Material,
    library_hint,
    material_for_density,
)

#: Largest mass error ε (module docstring) the default binning accepts.
DEFAULT_MAX_MASS_ERROR = 1e-3
#: Most materials the default binning makes before it stops short of the bound.
MAX_AUTO_BINS = 4096
#: Significant digits of the written densities (the binned masses use the rounded values).
DENSITY_DIGITS = 8


@dataclass(frozen=True)
class BinMaterial:
    """One exported material: id (1-based), unique name, composition (a tetdose material name
    of :data:`~tetdose.transport.physics.materials.MATERIALS`) and density [g/cm³]."""

    id: int
    name: str
    composition: str
    density_g_cm3: float


@dataclass(frozen=True, eq=False)
class BinnedPhase:
    """Per-tet material ids (1-based, into ``materials``), the materials, and the masses [g]
    before (exact, P1) and after binning."""

    material_id: IntArray
    materials: tuple[BinMaterial, ...]
    mass_g: FloatArray
    binned_mass_g: FloatArray

    @property
    def density_g_cm3(self) -> FloatArray:
        """(M,) binned density of each tet [g/cm³]."""
        rho = np.array([0.0] + [m.density_g_cm3 for m in self.materials])
        return rho[self.material_id]

    @property
    def mass_error(self) -> float:
        """ε = Σ|m_binned − m| / Σm (module docstring)."""
        return float(np.abs(self.binned_mass_g - self.mass_g).sum() / self.mass_g.sum())

    @property
    def total_mass_change(self) -> float:
        """Δ = (Σm_binned − Σm) / Σm."""
        return float((self.binned_mass_g.sum() - self.mass_g.sum()) / self.mass_g.sum())

    def summary(self) -> dict[str, object]:
        return {"materials": len(self.materials), "mass_g": float(self.mass_g.sum()),
                "mass_error": self.mass_error, "total_mass_change": self.total_mass_change}


def composition_classes(mean_density_g_cm3: FloatArray, region: IntArray | None,
                        region_materials: Mapping[int, str] | None = None,
                        compositions: Mapping[str, Material] | None = None
                        ) -> tuple[IntArray, list[str]]:
    """(class index per tet, class names): a region's material from ``region_materials``
    (label → name in :data:`MATERIALS` or ``compositions``, the plan's ``[materials.NAME]``),
    any other tet its density class."""
    names = list(DENSITY_CLASS_MATERIALS)
    cls = material_for_density(mean_density_g_cm3).astype(np.intp)
    for label, name in (region_materials or {}).items():
        if name not in MATERIALS and name not in (compositions or {}):
            raise PlanError(f"region {label}: material {name!r} is unknown; {library_hint(name)} "
                            f"or define it as [materials.{name}]")
        if region is None or not np.any(region == label):
            continue
        if name not in names:
            names.append(name)
        cls[region == label] = names.index(name)
    return cls, names


def bin_densities(mesh: TetMesh, density_g_cm3: FloatArray | None = None, *,
                  n_bins: int | None = None, max_mass_error: float = DEFAULT_MAX_MASS_ERROR,
                  region_materials: Mapping[int, str] | None = None,
                  compositions: Mapping[str, Material] | None = None) -> BinnedPhase:
    """Bin the mean tet densities of ``mesh`` into materials (module docstring).

    ``density_g_cm3``: vertex densities (default point_data ``density``); ``n_bins``: exactly
    this many materials at most (default: as few as keep ε ≤ ``max_mass_error``).
    """
    mass = tet_mass_g(mesh, density_g_cm3)
    if not mass.sum() > 0:
        raise DensityError("the mesh has no mass (all densities 0); map a density onto it first")
    volume_cm3 = mesh.volumes_mm3 / MM3_PER_CM3
    rho = mass / volume_cm3
    cls, names = composition_classes(rho, mesh.region, region_materials, compositions)
    used = np.unique(cls)
    if n_bins is not None and n_bins < len(used):
        raise OptionError(f"--density-bins {n_bins} is fewer than the {len(used)} composition "
                          f"classes present ({', '.join(names[c] for c in used)}); give at "
                          f"least {len(used)}")
    groups = _Groups(rho, volume_cm3, cls)
    limit = n_bins if n_bins is not None else MAX_AUTO_BINS
    # the written densities are rounded to DENSITY_DIGITS digits: keep room for that
    target = 0.0 if n_bins is not None else (max_mass_error - 10.0**-DENSITY_DIGITS) * float(
        mass.sum())
    while len(groups) < limit and groups.error() > target and groups.split_worst():
        pass
    return _binned(groups, names, mass, volume_cm3)


def _binned(groups: _Groups, names: list[str], mass: FloatArray, volume_cm3: FloatArray
            ) -> BinnedPhase:
    material_id = np.zeros(len(mass), dtype=np.intp)
    materials = []
    for g in sorted(groups.all(), key=lambda g: (g.cls, g.lo)):
        ids = groups.order[g.lo:g.hi]
        m_id = len(materials) + 1
        rho_b = float(f"{mass[ids].sum() / volume_cm3[ids].sum():.{DENSITY_DIGITS}g}")
        material_id[ids] = m_id
        materials.append(BinMaterial(m_id, f"{names[g.cls]}_{m_id}", names[g.cls], rho_b))
    rho = np.array([0.0] + [m.density_g_cm3 for m in materials])
    return BinnedPhase(material_id, tuple(materials), mass, volume_cm3 * rho[material_id])


@dataclass(frozen=True)
class _Group:
    """Tets order[lo:hi] of one class (sorted by density) and their Σ V |ρ − ρ_b| [g]."""

    error: float
    cls: int
    lo: int
    hi: int


class _Groups:
    """The groups of the greedy split, largest error first (a heap)."""

    def __init__(self, rho: FloatArray, volume: FloatArray, cls: IntArray) -> None:
        self.order = np.lexsort((rho, cls))
        self.rho, self.vol = rho[self.order], volume[self.order]
        self.w_cum = np.concatenate([[0.0], np.cumsum(self.vol)])
        self.wr_cum = np.concatenate([[0.0], np.cumsum(self.vol * self.rho)])
        starts = np.flatnonzero(np.diff(cls[self.order], prepend=-1))
        ends = np.append(starts[1:], len(rho))
        self.heap: list[tuple[float, int, int, int]] = []
        self.total = 0.0
        for lo, hi in zip(starts, ends, strict=True):
            self._push(int(cls[self.order[lo]]), int(lo), int(hi))

    def __len__(self) -> int:
        return len(self.heap)

    def error(self) -> float:
        return self.total

    def all(self) -> list[_Group]:
        return [_Group(-e, c, lo, hi) for e, c, lo, hi in self.heap]

    def _push(self, cls: int, lo: int, hi: int) -> None:
        err = float(_abs_dev(self.rho[lo:hi], self.w_cum, self.wr_cum, lo, np.array([hi]))[0])
        self.total += err
        heapq.heappush(self.heap, (-err, cls, lo, hi))

    def split_worst(self) -> bool:
        """Split the group with the largest error where the halves' errors sum least; False
        when no group can be split (every group holds one density)."""
        skipped = []
        done = False
        while self.heap and not done:
            neg, cls, lo, hi = heapq.heappop(self.heap)
            cut = self._best_cut(lo, hi) if -neg > 0 else None
            if cut is None:
                skipped.append((neg, cls, lo, hi))
                continue
            self.total += neg
            self._push(cls, lo, cut)
            self._push(cls, cut, hi)
            done = True
        for item in skipped:
            heapq.heappush(self.heap, item)
        return done

    def _best_cut(self, lo: int, hi: int) -> int | None:
        r = self.rho[lo:hi]
        cuts = lo + 1 + np.flatnonzero(np.diff(r) > 0)
        if not len(cuts):
            return None
        left = _abs_dev(r, self.w_cum, self.wr_cum, lo, cuts)
        right = _abs_dev(r, self.w_cum, self.wr_cum, cuts, np.full(len(cuts), hi), base=lo)
        return int(cuts[np.argmin(left + right)])


def _abs_dev(r: FloatArray, w_cum: FloatArray, wr_cum: FloatArray, lo: int | IntArray,
             hi: IntArray, base: int | None = None) -> FloatArray:
    """Σ_{lo≤k<hi} w_k |r_k − μ| with μ the w-weighted mean of the range, for each (lo, hi).

    ``r`` holds the sorted values from index ``base`` (default ``lo``); ``w_cum``/``wr_cum`` are
    global prefix sums of w and w·r. With p the first index whose r exceeds μ:
    Σ = μ(W[p] − W[lo]) − (R[p] − R[lo]) + (R[hi] − R[p]) − μ(W[hi] − W[p]).
    """
    base = int(lo) if base is None else base
    lo = np.broadcast_to(np.asarray(lo), hi.shape)
    w = w_cum[hi] - w_cum[lo]
    mu = (wr_cum[hi] - wr_cum[lo]) / w
    p = base + np.searchsorted(r, mu, side="right")
    p = np.clip(p, lo, hi)
    return np.maximum(mu * (w_cum[p] - w_cum[lo]) - (wr_cum[p] - wr_cum[lo])
                      + (wr_cum[hi] - wr_cum[p]) - mu * (w_cum[hi] - w_cum[p]), 0.0)
