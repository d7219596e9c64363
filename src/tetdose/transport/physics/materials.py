"""Named media (elemental mass fractions, nominal density, source) and the density-class rule.

**Library** (:data:`MATERIALS`, each entry's ``source`` names its reference):

- ICRU 44: ``water``, ``air``, ``lung``, ``adipose``, ``soft_tissue``, ``soft_tissue_4``,
  ``muscle``, ``blood``, ``cortical_bone``: the compositions of the NIST X-ray mass attenuation
  tables (Hubbell & Seltzer, NIST SRD 126, Table 2), which take the body tissues from ICRU
  Report 44 (1989), i.e. Woodard & White (Br. J. Radiol. 59:1209, 1986), also those of
  ICRU Report 46 (1992). With them the mixture rule μ/ρ = Σᵢ wᵢ (μ/ρ)ᵢ reproduces the NIST
  compound tables (:mod:`tetdose.transport.physics.xs`).
- ICRP Reference Man tissues as in ICRU Report 37 / NIST ESTAR (with ESTAR's I): ``icrp_cortical_bone``
  (1.85 g/cm³, EGSnrc's ICRPBONE), ``icrp_soft_tissue``, ``icrp_lung``, ``icrp_adipose``,
  ``icrp_skeletal_muscle``.
- ICRP Publication 110 (2009) adult reference computational phantoms, Annex B Tables B.1/B.2:
  all 53 media of each, ``icrp110_m_<medium>`` (male) and ``icrp110_f_<medium>`` (female), e.g.
  ``icrp110_m_mineral_bone``, ``icrp110_f_lumbar_spine_spongiosa``, ``icrp110_m_lung``,
  ``icrp110_f_air``. The earlier names ``icrp110_<medium>`` (mineral bone, teeth, spongiosa of
  cranium, pelvis, ribs and lumbar spine, medullary cavity, cartilage, skin, blood, muscle,
  liver, brain, heart, kidney, stomach, spleen, adipose, lung, miscellaneous soft tissue) remain,
  as the male media. ICRP-145 phantoms read by tetdose keep the compositions of their own
  ``.material`` file.
- ICRU Report 46 (1992) Table A.1 (Woodard & White 1986; White, Woodard & Hammond 1987): the
  adult and age-independent body tissues, ``icru46_<tissue>``: e.g. ``icru46_adipose_1`` … ``_3``,
  ``icru46_mammary_gland_1`` … ``_3``, ``icru46_liver``, ``icru46_lung`` (inflated, 0.26 g/cm³),
  ``icru46_cortical_bone``, ``icru46_cranium``, ``icru46_femur_30y``, ``icru46_spongiosa``,
  ``icru46_red_marrow``, ``icru46_yellow_marrow``, ``icru46_vertebra_d6_l3``, calculi.
  A table's fractions that do not sum to 1 (rounding) are stored normalised, with the table's
  sum (``table_sum``) and a note in ``source``.
- Phantom materials ``pmma``, ``polystyrene`` (ESTAR, with I), ``solid_water`` (RMI-457);
  implant metals ``titanium``, ``ti6al4v`` (ASTM F136), ``cocrmo`` (ASTM F75),
  ``stainless_steel_316l`` (ASTM F138), nominal compositions.

Any other composition is a :class:`~tetdose.core.composition.Material` (plan.toml
``[materials.NAME]`` tables). The nominal density of each medium is the one its density effect is
computed at; ``lung`` and ``icrp_lung`` carry inflated lung's 0.26 g/cm³ (:data:`LUNG_NOMINAL_G_CM3`),
not the 1.05 g/cm³ of ICRU 44's tissue sample (ICRP 110's lungs their phantoms' 0.382 and 0.385
g/cm³, ICRU 46's inflated lung 0.26 g/cm³, as tabulated).

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

import difflib
import json
from dataclasses import replace
from importlib import resources

import numpy as np

from tetdose._typing import FloatArray, IntArray
from tetdose.core.composition import Material, material_from_symbols
from tetdose.errors import PlanError

_ICRU44 = "ICRU Report 44 (1989) via NIST SRD 126 Table 2 (Hubbell & Seltzer)"
#: Nominal density [g/cm³] of the lung media (inflated lung; EGSnrc's LUNG521ICRU carries the
#: same): the density at which their density effect is computed.
LUNG_NOMINAL_G_CM3 = 0.26


def _m(name: str, rho: float, source: str, **fractions: float) -> Material:
    return material_from_symbols(name, fractions, rho, source)


def _library() -> tuple[Material, ...]:
    """The named media of ``data/compositions.json`` (sources in each entry), then its aliases
    (earlier names of some of them, e.g. ``icrp110_kidney`` = ``icrp110_m_kidneys``)."""
    text = resources.files("tetdose.transport.physics").joinpath("data/compositions.json")
    raw = json.loads(text.read_text())
    media = {name: material_from_symbols(name, d["composition"], d["density_g_cm3"], d["source"],
                                         d.get("mean_excitation_ev"))
             for name, d in raw["materials"].items()}
    aliases = tuple(replace(media[target], name=alias, source=f"{media[target].source} (= {target})")
                    for alias, target in raw["aliases"].items())
    return (*media.values(), *aliases)


#: Built-in materials by name. Sources: ICRU 44 via NIST SRD 126 Table 2.
MATERIALS: dict[str, Material] = {
    m.name: m
    for m in (
        _m("water", 1.0, "NIST SRD 126 Table 2 (Water, Liquid)", H=0.111894, O=0.888106),
        _m("air", 0.00120479, "NIST SRD 126 Table 2 (Air, Dry, near sea level)",
           C=0.000124, N=0.755268, O=0.231781, Ar=0.012827),
        _m("lung", LUNG_NOMINAL_G_CM3, _ICRU44 + " (Lung Tissue; nominal density 0.26 g/cm³ of "
           "inflated lung, not ICRU 44's 1.05, for the density effect)", H=0.103, C=0.105, N=0.031, O=0.749,
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
        *_library(),
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
        raise PlanError(f"unknown material {material!r}; {library_hint(material)} or pass a "
                        "Material") from None


def library_hint(name: str) -> str:
    """The end of an unknown-name message: the library's closest names and where it is listed
    (the library has ~200 names, too many to print)."""
    close = difflib.get_close_matches(name, MATERIALS, n=4, cutoff=0.5)
    near = f"closest: {', '.join(close)}; " if close else ""
    return (f"{near}choose a built-in medium (the {len(MATERIALS)} names of "
            "tetdose.transport.physics.materials.MATERIALS, listed in the user guide's physics page)")
