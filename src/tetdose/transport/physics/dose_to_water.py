"""Dose to water from dose to medium: the water-to-medium stopping-power ratio s_w,m.

Siebers, Keall, Nahum & Mohan (Phys. Med. Biol. 45:983, 2000) convert by Bragg–Gray cavity
theory: a small volume of water in place of medium m sees the medium's electron fluence, so

    D_w = D_m · s_w,m,    s_w,m = ∫ Φ_T (S_col/ρ)_w dT / ∫ Φ_T (S_col/ρ)_m dT,

with Φ_T the electron fluence differential in kinetic energy and S_col the unrestricted
collision stopping power (:func:`tetdose.transport.physics.electron_xs.collision_stopping_power`,
with each medium's density effect at its nominal density). They found the ratio nearly
constant through a field for a given beam (within ~1 % outside build-up), so one ratio per
medium and beam quality suffices; AAPM TG-105 (Chetty et al., Med. Phys. 34:4818, 2007) asks
Monte Carlo systems to say which dose they report.

**What tetdose does.** A dose-mode run tallies, per tet and voxel, the Spencer–Attix form of
this ratio over the electron fluence that cell actually tracks (restricted stopping powers
L_Δ, the tracks' own, plus the track-end term; :mod:`tetdose.transport.history._electron`,
:data:`TRACKED_METHOD`) and converts each cell by its own s_w,m. This module's per-medium
ratio is the documented fallback: for cells no electron crossed, for the ompMC engine and
imported doses. **The per-medium ratio (beam-quality spectrum)** weights by a documented
spectrum instead of a tallied fluence: the CSDA
slowing-down spectrum in water of the Compton electrons of a photon spectrum (default the 6 MV
spectrum of :func:`tetdose.plan.spectra.named_spectrum`, Mohan et al. 1985),

    Φ_T ∝ (1/S_col,w(T)) ∫_T^{T_max} s(T') dT',   s(T) = Σᵢ wᵢ dσ_KN/dT (Eᵢ, T),

(Attix, "Introduction to Radiological Physics", ch. 8: the equilibrium spectrum of a uniform
source; Klein–Nishina dσ/dT = π r_e²/(mc² k²) [2 + s²/(k²(1 − s)²) + s/(1 − s)(s − 2/k)],
s = T/E, k = E/mc²), on T from :data:`T_MIN_MEV` up. Pair electrons and delta rays are left
out: the ratio varies slowly with T (water/bone: 1.11 at 0.1 MeV, 1.12 at 5 MeV), so they move
it by < 0.2 %. Measured with this module: s_w,m = 1.114 for ICRP cortical bone (1.85 g/cm³;
Siebers et al.: ≈ 1.11), 1.010 ICRU soft tissue, 0.999 lung (at 0.26 g/cm³), 0.986 adipose,
1 for water exactly.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from tetdose._typing import FloatArray
from tetdose.plan.spectra import named_spectrum
from tetdose.transport.physics.electron_xs import ELECTRON, collision_stopping_power
from tetdose.transport.physics.materials import Material, resolve_material
from tetdose.transport.physics.xs import ELECTRON_MASS_MEV

#: Lowest electron energy of the average [MeV] (the electron cut-off scale of MC codes).
T_MIN_MEV = 0.01
#: Points of the kinetic-energy grid (log-spaced).
N_GRID = 600
#: The beam quality of the default spectrum.
DEFAULT_QUALITY = "6MV"
#: How a dose-mode run converts, for records (:func:`tetdose.transport.run.job.assemble`).
TRACKED_METHOD = ("per cell: Spencer-Attix s_w,m (restricted stopping powers, cut-off Δ, with "
                  "the track-end term) over the electron fluence each tet and voxel tracked "
                  "(Siebers et al. 2000); cells no electron crossed: the per-medium fallback")
#: How the per-medium fallback converts, for records.
METHOD = ("per medium: s_w,m averaged over the CSDA slowing-down spectrum in water of the "
          "Compton electrons of the {quality} photon spectrum (Siebers et al. 2000)")


def _kn_energy_spectrum(energy_mev: float, t_mev: FloatArray) -> FloatArray:
    """Klein–Nishina dσ/dT up to a constant, zero above the Compton edge (module docstring)."""
    k = energy_mev / ELECTRON_MASS_MEV
    s = np.minimum(t_mev / energy_mev, 1.0 - 1e-12)
    val = 2.0 + s * s / (k * k * (1.0 - s) ** 2) + s / (1.0 - s) * (s - 2.0 / k)
    t_edge = 2.0 * energy_mev**2 / (ELECTRON_MASS_MEV + 2.0 * energy_mev)
    return np.where(t_mev < t_edge, val / (k * k), 0.0)


@lru_cache(maxsize=8)
def electron_spectrum(quality: str = DEFAULT_QUALITY) -> tuple[FloatArray, FloatArray]:
    """(T [MeV], Φ_T up to a constant) in water for the named photon spectrum ``quality``."""
    energies, weights = named_spectrum(quality)
    t = np.geomspace(T_MIN_MEV, float(np.max(energies)), N_GRID)
    source = sum(w * _kn_energy_spectrum(float(e), t) for e, w in zip(energies, weights,
                                                                         strict=True))
    seg = 0.5 * (source[1:] + source[:-1]) * np.diff(t)
    above = np.concatenate((np.cumsum(seg[::-1])[::-1], [0.0]))
    phi = above / collision_stopping_power("water", ELECTRON, t)
    t.flags.writeable = phi.flags.writeable = False
    return t, phi


@lru_cache(maxsize=64)
def _ratio(material: Material, quality: str) -> float:
    t, phi = electron_spectrum(quality)
    s_w = collision_stopping_power("water", ELECTRON, t)
    s_m = collision_stopping_power(material, ELECTRON, t)
    return float(np.trapezoid(phi * s_w, t) / np.trapezoid(phi * s_m, t))


def water_to_medium_ratio(material: Material | str, quality: str = DEFAULT_QUALITY) -> float:
    """s_w,m of ``material`` for the beam quality ``quality`` (module docstring); exactly 1 for
    water."""
    mat = resolve_material(material)
    if mat == resolve_material("water"):
        return 1.0
    return _ratio(mat, quality)
