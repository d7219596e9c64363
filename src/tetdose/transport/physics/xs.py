"""Photon interaction data: per-process μ/ρ and μen/ρ tables on a uniform ln(E) grid.

**Attenuation.** Elemental cross sections per process come from the PyPI package ``mucoeff``
(Boone & Chavez 1996, Med. Phys. 23:1997, XCOM-based, 1 keV–50 MeV). A material's coefficients
follow the mixture rule μ/ρ = Σᵢ wᵢ (μ/ρ)ᵢ (Hubbell & Seltzer, NIST SRD 126). Elemental tables are
interpolated log–log; absorption edges (repeated energies in the table) are respected, the
energy just above an edge taking the upper branch. Processes: 0 coherent (Rayleigh),
1 incoherent (Compton), 2 photoelectric, 3 pair (nuclear + electron field, "triplet").

**Energy absorption.** μen/ρ = Σ_p (μ_p/ρ) · ⟨E_col⟩_p / E, with E_col the part of the secondary
electrons' kinetic energy T spent in collisions (Attix, "Introduction to Radiological Physics",
ch. 2; μen = μtr(1 − g)):

- photoelectric: μtr from mucoeff's photoelectric energy-absorption column (fluorescence escape
  removed), one photoelectron of T = E·μtr/μ;
- incoherent: free-electron Klein–Nishina energy transfer, N_A (Z/A) σ_KN ⟨T⟩_KN (binding lowers
  σ_incoh at low E mainly by removing low-T events, so the free-electron μtr is the better one);
- pair: T_total = E − 2mc² shared uniformly between electron and positron.

The radiative loss uses S_rad/S_col = a·T with a = Z̄/(700 MeV), Z̄ = Σwᵢ Zᵢ(Zᵢ+1)/Aᵢ / Σwᵢ Zᵢ/Aᵢ
(the textbook rule is Z·T/800 MeV; 700 MeV folds in annihilation in flight and makes water and
cortical bone agree with NIST μen/ρ within 1 % from 10 keV to 20 MeV). Then the collision part
of an electron's kinetic energy is T(1 − Y(T)) = ln(1 + aT)/a exactly.
(mucoeff's own μen/ρ is 1.4 % high at 200 keV and 3.6 % at 10 MeV in water, so it is not used.)

**Grid.** ``build_cross_sections`` samples every material on E_k = exp(ln_e_min + k·d_ln_e),
k = 0 … n−1, last point e_max. :func:`tetdose.transport.physics._photon.lookup` interpolates each
process log–log between nodes. The transport kernels read precomputed tables instead:
ln μ_t (μ_t = μ_incoh + μ_photo + μ_pair) and ln μen, interpolated linearly in ln E (log–log
interpolation of the total, two exp per call), and the branching fractions μ_incoh/μ_t and
μ_pair/μ_t, interpolated linearly in ln E (no transcendental function). Between nodes the total
differs from the sum of per-process log–log interpolations by the interpolation error only:
(h²/8)·Σ_p w_p (s_p − s̄)² at mid-interval (h = d_ln_e, s_p = d ln μ_p/d ln E, w_p = μ_p/μ_t,
s̄ = Σ_p w_p s_p). Measured on the 200-per-decade grid: ≤ 5.3e-5 relative (air at 28 keV, where
photoelectric and incoherent are comparable; ``tests/unit/test_physics_tables.py``), against
~1e-3 for either interpolation vs the direct evaluation. Coherent scattering is tabulated but
not transported (see :mod:`tetdose.transport.physics._photon`).

Tables are cached per (materials, e_min, e_max, points_per_decade), by name or composition, and
all arrays are read-only, so a cached table cannot be altered by a caller.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from functools import cache, lru_cache
from typing import NamedTuple

import numpy as np

from tetdose._constants import KEV_PER_MEV
from tetdose._typing import FloatArray
from tetdose.errors import PlanError
from tetdose.transport.physics.materials import (
    DENSITY_CLASS_MATERIALS,
    DENSITY_CLASS_UPPER_G_CM3,
    MATERIALS,
    Material,
    material_for_density,
    resolve_material,
)

__all__ = [
    "DENSITY_CLASS_MATERIALS",
    "DENSITY_CLASS_UPPER_G_CM3",
    "MATERIALS",
    "CrossSections",
    "Material",
    "build_cross_sections",
    "kn_cross_section_cm2",
    "mass_coefficients",
    "material_for_density",
    "transfer_coefficients",
]

#: Electron rest energy [MeV] (CODATA 2018).
ELECTRON_MASS_MEV = 0.51099895
#: Classical electron radius [cm] (CODATA 2018).
CLASSICAL_ELECTRON_RADIUS_CM = 2.8179403262e-13
#: Avogadro constant [1/mol].
AVOGADRO = 6.02214076e23
#: Radiative-yield constant [MeV] in S_rad/S_col = Z̄·T / constant (see module docstring).
RADIATIVE_CONSTANT_MEV = 700.0
#: Data range of mucoeff [MeV].
_DATA_E_MIN_MEV, _DATA_E_MAX_MEV = 0.001, 50.0
#: mucoeff table columns: photoelectric, coherent, incoherent, pair, triplet, μen photoelectric.
_COL_PHOTO, _COL_COH, _COL_INC, _COL_PAIR, _COL_TRIPLET, _COL_EN_PHOTO = 2, 3, 4, 5, 6, 12
_COLUMNS = (_COL_PHOTO, _COL_COH, _COL_INC, _COL_PAIR, _COL_TRIPLET, _COL_EN_PHOTO)
_GL_NODES = 128


class CrossSections(NamedTuple):
    """Flat interaction tables for kernels, uniform grid in ln(E).

    ``mu_rho_cm2_g[m, k, p]``: μ/ρ [cm²/g] of material m at E_k for process p
    (0 coherent, 1 incoherent, 2 photoelectric, 3 pair). ``mu_en_rho_cm2_g[m, k]``: μen/ρ
    [cm²/g]. E_k = exp(ln_e_min + k·d_ln_e) [MeV].

    Kernel tables on the same nodes (interpolated linearly in ln E by the transport kernels):
    ``ln_mu_transported[m, k]`` = ln(μ_incoh + μ_photo + μ_pair) [ln cm²/g] (μ_pair = 0 below
    2mc²), ``ln_mu_en[m, k]`` = ln(μen/ρ) [ln cm²/g], and the branching fractions
    ``p_incoherent[m, k]`` = μ_incoh/μ_t and ``p_pair[m, k]`` = μ_pair/μ_t [1] (photoelectric is
    the rest). All arrays are float64, C-contiguous and read-only.
    """

    ln_e_min: float
    d_ln_e: float
    mu_rho_cm2_g: np.ndarray
    mu_en_rho_cm2_g: np.ndarray
    ln_mu_transported: np.ndarray
    ln_mu_en: np.ndarray
    p_incoherent: np.ndarray
    p_pair: np.ndarray


@cache
def _element_table(z: int) -> tuple[FloatArray, FloatArray, float]:
    """(energies [MeV], columns (n, 15) of mucoeff, atomic mass [g/mol]) of element Z."""
    from mucoeff import Flag, mu
    from mucoeff.io.load import get_table

    table = np.ascontiguousarray(get_table(int(z)), dtype=np.float64)
    return table[:, 0] / KEV_PER_MEV, table, float(mu(Flag.ATOMIC_MASS, int(z)))


def _loglog(e_tab: FloatArray, y_tab: FloatArray, energy_mev: FloatArray) -> FloatArray:
    """Log–log interpolation of y(E); at a repeated energy (edge) the upper branch is used."""
    i = np.clip(np.searchsorted(e_tab, energy_mev, side="right"), 1, len(e_tab) - 1)
    e0, e1, y0, y1 = e_tab[i - 1], e_tab[i], y_tab[i - 1], y_tab[i]
    f = np.log(energy_mev / e0) / np.log(e1 / e0)
    positive = (y0 > 0.0) & (y1 > 0.0)
    ratio = np.where(positive, y1, 1.0) / np.where(positive, y0, 1.0)
    return np.where(positive, y0 * np.exp(f * np.log(ratio)), y0 + f * (y1 - y0))


def kn_cross_section_cm2(energy_mev: FloatArray) -> FloatArray:
    """Klein–Nishina total cross section per free electron [cm²] (Klein & Nishina 1929; Attix ch. 7)."""
    k = np.asarray(energy_mev, dtype=np.float64) / ELECTRON_MASS_MEV
    log_term = np.log1p(2.0 * k)
    return (2.0 * np.pi * CLASSICAL_ELECTRON_RADIUS_CM**2) * (
        (1.0 + k) / k**2 * (2.0 * (1.0 + k) / (1.0 + 2.0 * k) - log_term / k)
        + log_term / (2.0 * k)
        - (1.0 + 3.0 * k) / (1.0 + 2.0 * k) ** 2
    )


@cache
def _gauss_legendre() -> tuple[FloatArray, FloatArray]:
    """Gauss–Legendre nodes and weights on [−1, 1] (computed once: an eigenproblem each)."""
    return np.polynomial.legendre.leggauss(_GL_NODES)


def _kn_mean_fraction(energy_mev: FloatArray, a_per_mev: float) -> FloatArray:
    """⟨E_col(T)⟩_KN / E per Compton event, E_col = ln(1 + aT)/a (= T for a = 0).

    Gauss–Legendre in ε = E'/E ∈ [1/(1+2k), 1] with dσ/dε ∝ ε + 1/ε − sin²θ,
    1 − cos θ = (1/ε − 1)/k, T = E(1 − ε).
    """
    x, w = _gauss_legendre()
    e = np.asarray(energy_mev, dtype=np.float64)[:, None]
    k = e / ELECTRON_MASS_MEV
    eps0 = 1.0 / (1.0 + 2.0 * k)
    eps = eps0 + (1.0 - eps0) * (x[None, :] + 1.0) / 2.0
    t = (1.0 / eps - 1.0) / k
    density = eps + 1.0 / eps - t * (2.0 - t)
    kinetic = e * (1.0 - eps)
    collision = kinetic if a_per_mev == 0.0 else np.log1p(a_per_mev * kinetic) / a_per_mev
    return (density * collision) @ w / (density @ w) / e[:, 0]


def transfer_coefficients(material: Material | str, energy_mev: FloatArray) -> FloatArray:
    """μtr/ρ [cm²/g] of the transported model: the mean energy ``interact`` leaves locally.

    μtr/ρ = μ_photo/ρ + (μ_incoh/ρ)·⟨T⟩_KN/E + (μ_pair/ρ)(1 − 2mc²/E). It differs from μen/ρ
    by the radiative loss g (0.3 % at 1 MeV, ~3.5 % at 10 MeV in water), by fluorescence escape
    (bone, < 30 keV) and by binding in incoherent scattering (≤ 1.7 % in water at 50–150 keV):
    the analog (collision) tally scores this kerma, the track-length tally with μen/ρ scores
    collision kerma.
    """
    mu, _ = mass_coefficients(material, energy_mev)
    e = np.atleast_1d(np.asarray(energy_mev, dtype=np.float64))
    pair_fraction = np.maximum(1.0 - 2.0 * ELECTRON_MASS_MEV / e, 0.0)
    return mu[:, 2] + mu[:, 1] * _kn_mean_fraction(e, 0.0) + mu[:, 3] * pair_fraction


def mass_coefficients(
    material: Material | str, energy_mev: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Direct evaluation at any energies [MeV] in 1 keV–50 MeV.

    Returns ``(mu_rho (n, 4) [cm²/g] by process, mu_en_rho (n,) [cm²/g])``; formulas in the
    module docstring.
    """
    mat = resolve_material(material)
    e = np.atleast_1d(np.asarray(energy_mev, dtype=np.float64))
    if e.size and not (np.all(e >= _DATA_E_MIN_MEV) and np.all(e <= _DATA_E_MAX_MEV)):
        raise PlanError(f"photon energies must lie in {_DATA_E_MIN_MEV}–{_DATA_E_MAX_MEV} MeV")
    mu = np.zeros((e.size, 4))
    mu_en_photo = np.zeros(e.size)
    z_over_a = z2_over_a = 0.0
    for z, w in zip(mat.elements, mat.weights, strict=True):
        e_tab, tab, atomic_mass = _element_table(int(z))
        col = {c: _loglog(e_tab, tab[:, c], e) for c in _COLUMNS}
        mu[:, 0] += w * col[_COL_COH]
        mu[:, 1] += w * col[_COL_INC]
        mu[:, 2] += w * col[_COL_PHOTO]
        mu[:, 3] += w * (col[_COL_PAIR] + col[_COL_TRIPLET])
        mu_en_photo += w * col[_COL_EN_PHOTO]
        z_over_a += w * z / atomic_mass
        z2_over_a += w * z * (z + 1.0) / atomic_mass
    mu[e < 2.0 * ELECTRON_MASS_MEV, 3] = 0.0
    a = (z2_over_a / z_over_a) / RADIATIVE_CONSTANT_MEV  # S_rad/S_col per MeV of T
    t_photo = e * mu_en_photo / np.where(mu[:, 2] > 0.0, mu[:, 2], 1.0)
    photo = mu_en_photo * np.log1p(a * t_photo) / np.where(t_photo > 0, a * t_photo, 1.0)
    mu_kn = AVOGADRO * z_over_a * kn_cross_section_cm2(e)
    compton = mu_kn * _kn_mean_fraction(e, a)
    kin = np.maximum(e - 2.0 * ELECTRON_MASS_MEV, 0.0)  # (1/K)∫₀ᴷ ln(1+au) du, two leptons
    ak = a * kin
    pair_col = np.where(ak > 0, 2.0 * ((1.0 + ak) * np.log1p(ak) - ak) / np.where(ak > 0, ak, 1.0)
                        / a, 0.0)
    pair = mu[:, 3] * pair_col / e
    return mu, photo + compton + pair


def _warn_edges(mat: Material, e_min_mev: float, e_max_mev: float) -> None:
    from mucoeff import Flag, mu

    for z in mat.elements:
        for flag in (Flag.K_EDGE, Flag.L1_EDGE):
            edge_mev = float(mu(flag, int(z))) / KEV_PER_MEV
            if e_min_mev < edge_mev < e_max_mev:
                warnings.warn(
                    f"material {mat.name!r}: element Z={int(z)} has an absorption edge at "
                    f"{edge_mev * KEV_PER_MEV:.2f} keV inside the grid; the edge is smeared over one grid "
                    "interval (raise points_per_decade or e_min_mev)",
                    stacklevel=4,
                )


def build_cross_sections(
    material_names: Sequence[str | Material],
    e_min_mev: float = 0.01,
    e_max_mev: float = 20.0,
    points_per_decade: int = 200,
) -> CrossSections:
    """Tables of the given materials (names from :data:`MATERIALS`, or :class:`Material`).

    Material index m in the tables is the position in ``material_names``. The grid has
    n = ceil(decades·points_per_decade) + 1 points from e_min_mev to e_max_mev [MeV], uniform in
    ln(E). Raises :class:`PlanError` on unknown names or energies outside 1 keV–50 MeV.

    The result is cached by (materials, e_min_mev, e_max_mev, points_per_decade), names and
    :class:`Material` values alike (cached per composition): a repeated call returns the same
    read-only tables (and does not repeat the absorption-edge warnings).
    """
    return _cached_tables(tuple(material_names), e_min_mev, e_max_mev, points_per_decade)


def _frozen(a: FloatArray) -> FloatArray:
    """``a`` as a read-only, C-contiguous float64 array (copied only when it is not one)."""
    out = np.ascontiguousarray(a, dtype=np.float64)
    out.flags.writeable = False
    return out


def _tables(
    materials: tuple[str | Material, ...], e_min_mev: float, e_max_mev: float,
    points_per_decade: int,
) -> CrossSections:
    if not materials:
        raise PlanError("build_cross_sections needs at least one material")
    if not (_DATA_E_MIN_MEV <= e_min_mev < e_max_mev <= _DATA_E_MAX_MEV):
        raise PlanError(
            f"energy range {e_min_mev}–{e_max_mev} MeV is invalid; it must be increasing and "
            f"within {_DATA_E_MIN_MEV}–{_DATA_E_MAX_MEV} MeV"
        )
    if points_per_decade < 1:
        raise PlanError("points_per_decade must be a positive integer")
    n = math.ceil(math.log10(e_max_mev / e_min_mev) * points_per_decade) + 1
    ln_e_min = math.log(e_min_mev)
    d_ln_e = (math.log(e_max_mev) - ln_e_min) / (n - 1)
    energies = np.exp(ln_e_min + d_ln_e * np.arange(n))
    mu = np.empty((len(materials), n, 4))
    mu_en = np.empty((len(materials), n))
    for m, name in enumerate(materials):
        mat = resolve_material(name)
        _warn_edges(mat, e_min_mev, e_max_mev)
        mu[m], mu_en[m] = mass_coefficients(mat, energies)
    transported = mu[:, :, 1:].sum(axis=2)
    return CrossSections(
        ln_e_min, d_ln_e, _frozen(mu), _frozen(mu_en), _frozen(np.log(transported)),
        _frozen(np.log(mu_en)), _frozen(mu[:, :, 1] / transported),
        _frozen(mu[:, :, 3] / transported),
    )


_cached_tables = lru_cache(maxsize=32)(_tables)
