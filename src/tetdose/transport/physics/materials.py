"""Tissue compositions (elemental mass fractions) and the density-class material rule.

Compositions are those of the NIST X-ray mass attenuation tables (Hubbell & Seltzer, NIST SRD
126, Table 2), which take the body tissues from ICRU Report 44 (1989), "Tissue Substitutes in
Radiation Dosimetry and Measurement". With them, the mixture rule
μ/ρ = Σᵢ wᵢ (μ/ρ)ᵢ reproduces the NIST compound tables (see :mod:`tetdose.transport.physics.xs`).

Density classes (Schneider et al. 2000, Phys. Med. Biol. 45:459, style): a voxel or tetrahedron
without a region label gets the material of the class its mass density falls in. Schneider bins
tissue by HU (air < −950, lung < −120, adipose < ~20, soft tissue, bone ≥ 120 HU); we bin by
density, so that mapped and moved densities need no HU, with boundaries chosen so that inflated
lung (~0.26), fat (~0.95), water-like tissue (1.0–1.07) and bone (> 1.1 g/cm³) sit well inside
their classes. The last column gives the HU of each boundary on the
default Schneider 2000 curve (:meth:`tetdose.core.calibration.HUCalibration.schneider2000`):

======================  =====================  ===========================
material                density [g/cm³]        HU on the Schneider curve
======================  =====================  ===========================
air                     ρ < 0.05               HU < −953
lung                    0.05 ≤ ρ < 0.85        −953 ≤ HU < −176
adipose                 0.85 ≤ ρ < 0.985       −176 ≤ HU < −36
soft_tissue             0.985 ≤ ρ < 1.10       −36 ≤ HU < 83
cortical_bone           ρ ≥ 1.10               HU ≥ 83
======================  =====================  ===========================

Densities between ~1.1 and 1.9 g/cm³ are a spongy-bone mixture in reality; here they get cortical
bone's composition (at the density of the voxel), which over-states the calcium fraction. Give
bone a region label with its own material when this matters.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tetdose._typing import FloatArray, IntArray
from tetdose.errors import PlanError

_ICRU44 = "ICRU Report 44 (1989) via NIST SRD 126 Table 2 (Hubbell & Seltzer)"


@dataclass(frozen=True)
class Material:
    """A homogeneous material: elemental mass fractions by atomic number Z.

    ``mass_fractions`` is a tuple of ``(Z, w)`` pairs with Σw = 1 (checked to 1e-3 and used
    normalised); ``density_g_cm3`` is the nominal density [g/cm³] (transport uses the mapped
    density, this one is for reference); ``source`` names where the composition comes from.
    """

    name: str
    mass_fractions: tuple[tuple[int, float], ...]
    density_g_cm3: float
    source: str

    def __post_init__(self) -> None:
        if not self.mass_fractions:
            raise PlanError(f"material {self.name!r} has no elements; give (Z, fraction) pairs")
        for z, w in self.mass_fractions:
            if not (1 <= int(z) <= 100) or not (w >= 0.0):
                raise PlanError(
                    f"material {self.name!r}: element ({z}, {w}) is invalid; Z must be 1…100 "
                    "and the mass fraction non-negative"
                )
        total = sum(w for _, w in self.mass_fractions)
        if abs(total - 1.0) > 1e-3:
            raise PlanError(
                f"material {self.name!r}: mass fractions sum to {total:.6f}, not 1; "
                "fix the composition"
            )
        if not self.density_g_cm3 > 0.0:
            raise PlanError(f"material {self.name!r}: nominal density must be > 0 g/cm³")

    @property
    def elements(self) -> IntArray:
        """Atomic numbers Z of the constituents."""
        return np.array([z for z, _ in self.mass_fractions], dtype=np.intp)

    @property
    def weights(self) -> FloatArray:
        """Mass fractions, normalised to sum to 1."""
        w = np.array([w for _, w in self.mass_fractions], dtype=np.float64)
        return w / w.sum()


def _m(name: str, rho: float, source: str, **fractions: float) -> Material:
    z_of = {"H": 1, "C": 6, "N": 7, "O": 8, "Na": 11, "Mg": 12, "P": 15, "S": 16, "Cl": 17,
            "Ar": 18, "K": 19, "Ca": 20, "Fe": 26}
    return Material(name, tuple((z_of[s], w) for s, w in fractions.items()), rho, source)


#: Built-in materials by name. Sources: ICRU 44 via NIST SRD 126 Table 2.
MATERIALS: dict[str, Material] = {
    m.name: m
    for m in (
        _m("water", 1.0, "NIST SRD 126 Table 2 (Water, Liquid)", H=0.111894, O=0.888106),
        _m("air", 0.00120479, "NIST SRD 126 Table 2 (Air, Dry, near sea level)",
           C=0.000124, N=0.755268, O=0.231781, Ar=0.012827),
        _m("lung", 1.05, _ICRU44 + " (Lung Tissue)", H=0.103, C=0.105, N=0.031, O=0.749,
           Na=0.002, P=0.002, S=0.003, Cl=0.003, K=0.002),
        _m("adipose", 0.95, _ICRU44 + " (Adipose Tissue)", H=0.114, C=0.598, N=0.007,
           O=0.278, Na=0.001, S=0.001, Cl=0.001),
        _m("soft_tissue", 1.06, _ICRU44 + " (Tissue, Soft)", H=0.102, C=0.143, N=0.034,
           O=0.708, Na=0.002, P=0.003, S=0.003, Cl=0.002, K=0.003),
        _m("soft_tissue_4", 1.0, _ICRU44 + " (Tissue, Soft, ICRU four-component)",
           H=0.101172, C=0.111, N=0.026, O=0.761828),
        _m("muscle", 1.05, _ICRU44 + " (Muscle, Skeletal)", H=0.102, C=0.143, N=0.034,
           O=0.710, Na=0.001, P=0.002, S=0.003, Cl=0.001, K=0.004),
        _m("blood", 1.06, _ICRU44 + " (Blood, Whole)", H=0.102, C=0.110, N=0.033, O=0.745,
           Na=0.001, P=0.001, S=0.002, Cl=0.003, K=0.002, Fe=0.001),
        _m("cortical_bone", 1.92, _ICRU44 + " (Bone, Cortical)", H=0.034, C=0.155, N=0.042,
           O=0.435, Na=0.001, Mg=0.002, P=0.103, S=0.003, Ca=0.225),
    )
}

#: Default material list of the density classes; index i is class i.
DENSITY_CLASS_MATERIALS: tuple[str, ...] = ("air", "lung", "adipose", "soft_tissue",
                                            "cortical_bone")
#: Upper density bound [g/cm³] of each class but the last (see the module docstring).
DENSITY_CLASS_UPPER_G_CM3: tuple[float, ...] = (0.05, 0.85, 0.985, 1.10)


def material_for_density(density_g_cm3: FloatArray) -> IntArray:
    """Density class of each density [g/cm³]: an index into :data:`DENSITY_CLASS_MATERIALS`.

    Class i holds ``UPPER[i-1] ≤ ρ < UPPER[i]`` with ``UPPER`` = :data:`DENSITY_CLASS_UPPER_G_CM3`
    (``np.searchsorted(UPPER, ρ, side="right")``). Returns an intp array of the input's shape.
    Raises :class:`PlanError` on NaN or negative densities.
    """
    rho = np.asarray(density_g_cm3, dtype=np.float64)
    if not np.all(rho >= 0.0):
        raise PlanError(
            "densities must be finite and non-negative to choose a material by density class; "
            "fix the density map (NaN or negative values found)"
        )
    upper = np.asarray(DENSITY_CLASS_UPPER_G_CM3, dtype=np.float64)
    return np.searchsorted(upper, rho, side="right").astype(np.intp)


def resolve_material(material: Material | str) -> Material:
    """A :class:`Material`, or the one of :data:`MATERIALS` named ``material``."""
    if isinstance(material, Material):
        return material
    try:
        return MATERIALS[material]
    except KeyError:
        raise PlanError(
            f"unknown material {material!r}; choose one of {sorted(MATERIALS)} or pass a Material"
        ) from None
