"""Material compositions: elemental mass fractions, nominal density, mean excitation energy.

A :class:`Material` is plain data, so the plan (``[materials.NAME]`` tables in plan.toml,
:mod:`tetdose.plan.model`), the CT calibration (Schneider's HU → composition bins,
:mod:`tetdose.core.calibration`) and the transport's interaction tables
(:mod:`tetdose.transport.physics`) share one definition. The built-in library of named media is
:mod:`tetdose.transport.physics.materials`.

``density_g_cm3`` is the **nominal** density: the density at which the density-effect correction
δ of the collision stopping power is computed (Sternheimer; ICRU Report 37 §4) and which is
recorded with the medium. Transport always uses the mapped density of each cell (mass per
volume), so a lung at 0.26 g/cm³ and one at 0.4 g/cm³ differ in mass, with the δ of the
material's nominal density.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from tetdose._typing import FloatArray, IntArray
from tetdose.errors import PlanError

#: Element symbols by atomic number Z = 1 … 98 (the range of tetdose's photon and electron data).
SYMBOLS: tuple[str, ...] = (
    "H", "He", "Li", "Be", "B", "C", "N", "O", "F", "Ne", "Na", "Mg", "Al", "Si", "P", "S", "Cl",
    "Ar", "K", "Ca", "Sc", "Ti", "V", "Cr", "Mn", "Fe", "Co", "Ni", "Cu", "Zn", "Ga", "Ge", "As",
    "Se", "Br", "Kr", "Rb", "Sr", "Y", "Zr", "Nb", "Mo", "Tc", "Ru", "Rh", "Pd", "Ag", "Cd", "In",
    "Sn", "Sb", "Te", "I", "Xe", "Cs", "Ba", "La", "Ce", "Pr", "Nd", "Pm", "Sm", "Eu", "Gd", "Tb",
    "Dy", "Ho", "Er", "Tm", "Yb", "Lu", "Hf", "Ta", "W", "Re", "Os", "Ir", "Pt", "Au", "Hg", "Tl",
    "Pb", "Bi", "Po", "At", "Rn", "Fr", "Ra", "Ac", "Th", "Pa", "U", "Np", "Pu", "Am", "Cm", "Bk",
    "Cf")
#: Atomic number by element symbol.
Z_OF: dict[str, int] = {s: z for z, s in enumerate(SYMBOLS, start=1)}
#: Tolerance on Σ mass fractions = 1.
SUM_TOLERANCE = 1e-3


@dataclass(frozen=True)
class Material:
    """A homogeneous material: elemental mass fractions by atomic number Z.

    ``mass_fractions`` is a tuple of ``(Z, w)`` pairs with Σw = 1 (checked to
    :data:`SUM_TOLERANCE` and used normalised); ``density_g_cm3`` is the nominal density
    [g/cm³] (the density effect's, module docstring); ``source`` names where the composition
    comes from; ``mean_excitation_ev`` is the mean excitation energy I [eV] (None: ICRU 37's
    Bragg rule, :func:`tetdose.transport.physics.electron_xs.mean_excitation_ev`). Frozen and
    hashable: interaction tables are cached per composition.
    """

    name: str
    mass_fractions: tuple[tuple[int, float], ...]
    density_g_cm3: float
    source: str
    mean_excitation_ev: float | None = None

    def __post_init__(self) -> None:
        if not self.mass_fractions:
            raise PlanError(f"material {self.name!r} has no elements; give (Z, fraction) pairs")
        for z, w in self.mass_fractions:
            if not (1 <= int(z) <= len(SYMBOLS)) or not (w >= 0.0):
                raise PlanError(
                    f"material {self.name!r}: element ({z}, {w}) is invalid; Z must be "
                    f"1…{len(SYMBOLS)} and the mass fraction non-negative"
                )
        total = sum(w for _, w in self.mass_fractions)
        if abs(total - 1.0) > SUM_TOLERANCE:
            raise PlanError(
                f"material {self.name!r}: mass fractions sum to {total:.6f}, not 1 (±"
                f"{SUM_TOLERANCE:g}); fix the composition"
            )
        if not (math.isfinite(self.density_g_cm3) and self.density_g_cm3 > 0.0):
            raise PlanError(f"material {self.name!r}: nominal density must be > 0 g/cm³")
        i_ev = self.mean_excitation_ev
        if i_ev is not None and not (math.isfinite(i_ev) and 10.0 <= i_ev <= 1000.0):
            raise PlanError(f"material {self.name!r}: mean_excitation_ev = {i_ev} is not a "
                            "mean excitation energy (10–1000 eV)")

    @property
    def elements(self) -> IntArray:
        """Atomic numbers Z of the constituents."""
        return np.array([z for z, _ in self.mass_fractions], dtype=np.intp)

    @property
    def weights(self) -> FloatArray:
        """Mass fractions, normalised to sum to 1."""
        w = np.array([w for _, w in self.mass_fractions], dtype=np.float64)
        return w / w.sum()

    def record(self) -> dict[str, object]:
        """JSON-ready description: mass fractions by symbol, nominal density, I, source."""
        return {"composition": {SYMBOLS[int(z) - 1]: float(w) for z, w in self.mass_fractions},
                "density_g_cm3": self.density_g_cm3,
                "mean_excitation_ev": self.mean_excitation_ev, "source": self.source}


def material_from_symbols(name: str, fractions: Mapping[str, float], density_g_cm3: float,
                          source: str, mean_excitation_ev: float | None = None) -> Material:
    """A :class:`Material` from mass fractions by element symbol (``{"H": 0.102, ...}``)."""
    pairs = []
    for symbol, w in fractions.items():
        if symbol not in Z_OF:
            raise PlanError(f"material {name!r}: {symbol!r} is not an element symbol (H, He, "
                            "… Cf; case matters: Ca, not CA)")
        try:
            pairs.append((Z_OF[symbol], float(w)))
        except (TypeError, ValueError):
            raise PlanError(f"material {name!r}: the mass fraction of {symbol} must be a "
                            f"number, got {w!r}") from None
    return Material(name, tuple(pairs), float(density_g_cm3), source, mean_excitation_ev)


def material_from_table(name: str, table: Mapping[str, object], where: str) -> Material:
    """A :class:`Material` from a plan.toml ``[materials.NAME]`` table: ``composition`` (mass
    fractions by symbol, summing to 1 within :data:`SUM_TOLERANCE`), ``density`` [g/cm³] and
    optional ``mean_excitation_ev`` [eV]; ``where`` names the table in messages."""
    unknown = set(table) - {"composition", "density", "mean_excitation_ev", "source"}
    if unknown:
        raise PlanError(f"{where}: unknown key(s) {sorted(unknown)}; use composition, density, "
                        "mean_excitation_ev (and source)")
    comp = table.get("composition")
    if not isinstance(comp, Mapping) or not comp:
        raise PlanError(f"{where}: give composition = {{H = 0.102, C = 0.143, …}} (mass "
                        "fractions by element symbol)")
    try:
        density = float(table["density"])  # type: ignore[arg-type]
    except KeyError:
        raise PlanError(f"{where}: give density = … (g/cm³)") from None
    except (TypeError, ValueError):
        raise PlanError(f"{where}: density must be a number (g/cm³)") from None
    i_ev = table.get("mean_excitation_ev")
    return material_from_symbols(name, comp, density, str(table.get("source", where)),
                                 None if i_ev is None else float(i_ev))  # type: ignore[arg-type]
