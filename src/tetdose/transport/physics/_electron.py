"""Electron and positron interaction kernels for class II condensed history (numba).

All kernels read :class:`tetdose.transport.physics.electron_xs.ElectronTables` ``et`` (material
index ``m``, species ``sp``: 0 electron, 1 positron), take kinetic energies in MeV and mass
thicknesses in g/cm², and return the new RNG state first when they sample
(:func:`tetdose._random.next_uniform`). Formulas and sources:

- tables are linear in ln T between the nodes T_k = exp(ln_e_min + k·d_ln_e);
  :func:`energy_at_range` is the exact inverse of :func:`range_of` (same interpolant), so
  ``energy_at_range(range_of(T) − s)`` is the CSDA energy after a path of mass thickness s;
- Møller (e⁻e⁻) and Bhabha (e⁺e⁻) delta rays above the cut-off Δ: the DCS of Kawrakow &
  Rogers, PIRS-701 (EGSnrc manual) §2.4, sampled as 1/ε² times a rejection function
  (ε = W/T, W the delta ray's kinetic energy; Møller ε ∈ [Δ/T, 1/2], Bhabha ε ∈ [Δ/T, 1]);
  polar angles from two-body kinematics, cos θ = sqrt(T_out (T + 2mc²) / (T (T_out + 2mc²)));
- bremsstrahlung photon energy k = κT above k_c: the Bethe–Heitler DCS with Thomas–Fermi
  screening (Koch & Motz 1959, 3BS(e); screening functions of Butcher & Messel 1960, as in EGS4,
  SLAC-265 §2.7), k dσ/dk ∝ χ(κ) = (1 + ε²)(φ₁(δ) − c) − (2/3) ε (φ₂(δ) − c), ε = E'/E,
  δ = 136 mc² k / (Z^{1/3} E E'), c = (4/3) ln Z (E, E' total energies before/after), sampled
  as 1/κ on [k_c/T, 1] times χ/χ_max with χ_max = 2(20.867 − c) (χ ≤ χ_max for every δ);
  the photon polar angle from the leading term of Koch & Motz 2BS, p(cos θ) ∝ (1 − β cos θ)⁻²
  (the θ ≈ mc²/E law; Bielajew, Mohan & Chen 1989), sampled by inversion;
- positron annihilation in flight: Heitler's DCS (PENELOPE-2008 manual, Salvat et al., §3.4),
  dσ/dζ ∝ S(ζ) + S(1 − ζ), S(ζ) = −(γ + 1)² + (γ² + 4γ + 1)/ζ − 1/ζ², ζ = k₁/(T + 2mc²) ∈
  [ζ_min, 1 − ζ_min], ζ_min = 1/(γ + 1 + sqrt(γ² − 1)); cos θᵢ = (γ + 1 − 1/ζᵢ)/sqrt(γ² − 1);
- multiple elastic scattering over a step s: a distribution with the exact Goudsmit–Saunderson
  first and second moments, ⟨1 − μ⟩ = G₁ = 1 − exp(−s/λ₁) and ⟨P₂(μ)⟩ = exp(−s/λ₂), i.e.
  ⟨(1 − μ)²⟩ = T₂ = (3G₁ − G₂)/(3/2) with G₂ = 1 − exp(−s/λ₂) (the random hinge then gives the
  spatial moments of the step to second order, Kawrakow & Bielajew 1998; with the first moment
  alone the spread, and so the practical range of electron beams, grows with the step size).
  The base is the Wentzel (screened Rutherford) shape p_W(μ) ∝ (1 − μ + 2A)⁻² with A solved so
  that ⟨1 − μ⟩ = 2A[(1 + A) ln(1 + 1/A) − 1] = G₁ (the shape of PENELOPE's and Geant4
  WentzelVI's models), sampled as μ = 1 − 2Au/(1 + A − u). Its second moment
  M₂(A) = 2A(1 + A)[2 + 2A − 2A²/(1 + A) − 4A ln(1 + 1/A)] exceeds T₂ for the steps of the
  transport (by 70 % at s/λ₁ = 0.1, 2 MeV in water); the excess is removed by a mixture with a fixed
  deflection at the mean, p = (1 − B) p_W + B δ(1 − μ − G₁), B = (M₂ − T₂)/(M₂ − G₁²), which
  keeps the first moment and gives T₂ exactly (an artificial law with the two exact moments, as
  PENELOPE uses for its soft scattering; tests/verification/test_electron_beams.py shows the step
  size no longer moves R50 or Rp). Isotropic when
  exp(−s/λ₁) < 1e-6.
"""

import math

import numpy as np

from tetdose._jit import kernel
from tetdose._random import next_uniform

#: Electron rest energy [MeV] (CODATA 2018; the same value as electron_xs.ELECTRON_MASS_MEV).
_MC2 = 0.51099895
#: exp(−s/λ₁) below this: the direction after the step is isotropic (⟨1 − μ⟩ within 1e-6).
_ISOTROPIC_X = 13.815510557964274  # −ln(1e-6)


@kernel
def electron_position(et, e):
    """Grid cell and fraction (i, f) of kinetic energy e [MeV]: ln e = ln_e_min + (i + f)·d_ln_e.

    Clamped to the table: below the first node (0, 0.0), above the last (n − 2, 1.0).
    """
    n = et.stopping.shape[2]
    x = (math.log(e) - et.ln_e_min) / et.d_ln_e
    if not x > 0.0:
        return 0, 0.0
    i = int(x)
    if i >= n - 1:
        return n - 2, 1.0
    return i, x - i


@kernel
def stopping_power(et, m, sp, e):
    """Restricted total mass stopping power L/ρ [MeV cm²/g] at kinetic energy e [MeV]."""
    i, f = electron_position(et, e)
    return (1.0 - f) * et.stopping[m, sp, i] + f * et.stopping[m, sp, i + 1]


@kernel
def range_of(et, m, sp, e):
    """Restricted range ∫_cut-off^e dT/L(T) [g/cm²] (0 at and below the cut-off)."""
    i, f = electron_position(et, e)
    return (1.0 - f) * et.range_g_cm2[m, sp, i] + f * et.range_g_cm2[m, sp, i + 1]


@kernel
def energy_at_range(et, m, sp, r):
    """Kinetic energy [MeV] whose restricted range is r [g/cm²]: the inverse of :func:`range_of`.

    r ≤ 0 gives the cut-off energy (the particle stops); r beyond the table the last node.
    """
    table = et.range_g_cm2[m, sp]
    n = table.shape[0]
    if not r > 0.0:
        return math.exp(et.ln_e_min)
    if r >= table[n - 1]:
        return math.exp(et.ln_e_min + (n - 1) * et.d_ln_e)
    lo = 0
    hi = n - 1
    while hi - lo > 1:  # table[lo] <= r < table[hi]
        mid = (lo + hi) >> 1
        if table[mid] <= r:
            lo = mid
        else:
            hi = mid
    f = (r - table[lo]) / (table[hi] - table[lo])
    return math.exp(et.ln_e_min + (lo + f) * et.d_ln_e)


@kernel
def hard_cross_sections(et, m, sp, e):
    """(σ_delta, σ_brems, σ_annih) [cm²/g] at e [MeV]: Møller/Bhabha above Δ, bremsstrahlung
    above k_c, annihilation in flight (0 for electrons)."""
    i, f = electron_position(et, e)
    g = 1.0 - f
    s_delta = g * et.sigma_delta[m, sp, i] + f * et.sigma_delta[m, sp, i + 1]
    s_brems = g * et.sigma_brems[m, sp, i] + f * et.sigma_brems[m, sp, i + 1]
    s_annih = 0.0
    if sp == 1:
        s_annih = g * et.sigma_annih[m, i] + f * et.sigma_annih[m, i + 1]
    return s_delta, s_brems, s_annih


@kernel
def lambda1_inverse(et, m, sp, e):
    """First transport mass cross section 1/λ₁ [cm²/g] at e [MeV]."""
    i, f = electron_position(et, e)
    return (1.0 - f) * et.lambda1_inv[m, sp, i] + f * et.lambda1_inv[m, sp, i + 1]


@kernel
def binary_cos(t_out, t_in):
    """cos θ of a particle leaving a free-electron collision with kinetic energy t_out [MeV]
    from an incident one of t_in [MeV] (two-body kinematics, equal masses)."""
    c2 = t_out * (t_in + 2.0 * _MC2) / (t_in * (t_out + 2.0 * _MC2))
    return math.sqrt(min(c2, 1.0))


@kernel
def moller_rejection(eps, tau):
    """ε²·(Møller DCS bracket) = 1 + r² + g²ε² − g₃ r, r = ε/(1 − ε), g = τ/(τ + 1),
    g₃ = (2τ + 1)/(τ + 1)²; at most 1 + 1.25 g² on ε ∈ (0, 1/2]."""
    g = tau / (tau + 1.0)
    g3 = (2.0 * tau + 1.0) / ((tau + 1.0) * (tau + 1.0))
    r = eps / (1.0 - eps)
    return 1.0 + r * r + g * g * eps * eps - g3 * r


@kernel
def sample_moller(e, cutoff, state):
    """Møller delta ray of an electron of e [MeV] above ``cutoff`` [MeV].

    Returns (state, t_delta [MeV], cos_primary, cos_delta); the primary keeps e − t_delta.
    When e < 2·cutoff no collision is possible and t_delta = 0 is returned.
    """
    eps0 = cutoff / e
    if eps0 >= 0.5:
        return state, 0.0, 1.0, 1.0
    tau = e / _MC2
    g = tau / (tau + 1.0)
    bound = 1.0 + 1.25 * g * g
    span = 1.0 - 2.0 * eps0
    while True:
        state, u1 = next_uniform(state)
        state, u2 = next_uniform(state)
        eps = eps0 / (1.0 - u1 * span)
        if u2 * bound <= moller_rejection(eps, tau):
            break
    t_delta = eps * e
    t_prim = e - t_delta
    return state, t_delta, binary_cos(t_prim, e), binary_cos(t_delta, e)


@kernel
def bhabha_rejection(eps, tau):
    """β²ε²·(Bhabha DCS bracket) = 1 − β²ε(B₁ − ε(B₂ − ε(B₃ − εB₄))) ∈ [0, 1] (PIRS-701 §2.4.3)."""
    y = 1.0 / (tau + 2.0)
    y2 = y * y
    c = 1.0 - 2.0 * y
    b1 = 2.0 - y2
    b2 = c * (3.0 + y2)
    b4 = c * c * c
    b3 = b4 + c * c
    beta2 = tau * (tau + 2.0) / ((tau + 1.0) * (tau + 1.0))
    return 1.0 - beta2 * eps * (b1 - eps * (b2 - eps * (b3 - eps * b4)))


@kernel
def sample_bhabha(e, cutoff, state):
    """Bhabha collision of a positron of e [MeV]: the electron set in motion gets t_delta ≥ cutoff.

    Returns (state, t_delta [MeV], cos_positron, cos_electron); the positron keeps e − t_delta.
    When e ≤ cutoff no collision is possible and t_delta = 0 is returned.
    """
    eps0 = cutoff / e
    if eps0 >= 1.0:
        return state, 0.0, 1.0, 1.0
    tau = e / _MC2
    span = 1.0 - eps0
    while True:
        state, u1 = next_uniform(state)
        state, u2 = next_uniform(state)
        eps = eps0 / (1.0 - u1 * span)
        if u2 <= bhabha_rejection(eps, tau):
            break
    t_delta = eps * e
    t_pos = e - t_delta
    return state, t_delta, binary_cos(t_pos, e), binary_cos(t_delta, e)


@kernel
def brems_chi(z13, c, t, kappa):
    """Screened Bethe–Heitler shape χ = k dσ/dk (arbitrary units, ≥ 0) for photon energy κ·t.

    ``z13`` = Z^{1/3}, ``c`` = (4/3) ln Z of the material's effective Z, t [MeV] the electron's
    kinetic energy, κ ∈ (0, 1]. Formula in the module docstring.
    """
    e0 = t + _MC2
    k = kappa * t
    e1 = e0 - k
    eps = e1 / e0
    delta = 136.0 * _MC2 * k / (z13 * e0 * e1)
    if delta <= 1.0:
        phi1 = 20.867 - 3.242 * delta + 0.625 * delta * delta
        phi2 = 20.029 - 1.930 * delta - 0.086 * delta * delta
    else:
        phi1 = 21.12 - 4.184 * math.log(delta + 0.952)
        phi2 = phi1
    chi = (1.0 + eps * eps) * (phi1 - c) - (2.0 / 3.0) * eps * (phi2 - c)
    return max(chi, 0.0)


@kernel
def brems_chi_table(z13, c, t_mev, kappa, out):
    """out[i, j] = :func:`brems_chi` (z13, c, t_mev[i], kappa[i, j]) (used to build the tables)."""
    for i in range(kappa.shape[0]):
        for j in range(kappa.shape[1]):
            out[i, j] = brems_chi(z13, c, t_mev[i], kappa[i, j])


@kernel
def sample_dipole_cos(e, u):
    """cos θ from p(cos θ) ∝ (1 − β cos θ)⁻² for a lepton of kinetic energy e [MeV], by inversion
    of the CDF at u ∈ [0, 1): cos θ = (2u − 1 + β)/(1 − β + 2βu)."""
    gamma = e / _MC2 + 1.0
    beta = math.sqrt(max(1.0 - 1.0 / (gamma * gamma), 0.0))
    one_minus_beta = 1.0 / (gamma * gamma * (1.0 + beta))
    cos_t = (2.0 * u - one_minus_beta) / (one_minus_beta + 2.0 * beta * u)
    return min(max(cos_t, -1.0), 1.0)


@kernel
def sample_brems(et, m, sp, e, state):
    """Bremsstrahlung photon above k_c = et.photon_cutoff_mev from a lepton of e [MeV].

    Returns (state, k_photon [MeV], cos_photon); the lepton keeps e − k_photon and its
    direction. When e ≤ k_c, (state, 0.0, 1.0). The spectrum shape is the same for positrons
    (only the total, in the tables, differs).
    """
    kc = et.photon_cutoff_mev
    if e <= kc:
        return state, 0.0, 1.0
    z13 = et.brems_z13[m]
    c = et.brems_c[m]
    bound = 2.0 * (20.867 - c)
    ln_kc = math.log(kc / e)
    while True:
        state, u1 = next_uniform(state)
        state, u2 = next_uniform(state)
        kappa = math.exp(ln_kc * (1.0 - u1))
        if u2 * bound <= brems_chi(z13, c, e, kappa):
            break
    state, u3 = next_uniform(state)
    return state, kappa * e, sample_dipole_cos(e, u3)


@kernel
def sample_annihilation_in_flight(e, state):
    """Two photons from a positron of kinetic energy e [MeV] annihilating with a free electron.

    Returns (state, k1, cos1, k2, cos2): energies [MeV] with k1 + k2 = e + 2mc², polar angles
    to the positron direction; photon 2 has the opposite azimuth. Below e = 1e-9 MeV the pair
    is emitted back to back in an isotropic direction.
    """
    etot = e + 2.0 * _MC2
    gamma = e / _MC2 + 1.0
    p = math.sqrt(e / _MC2 * (e / _MC2 + 2.0))  # sqrt(γ² − 1)
    if p < 1e-9:
        state, u = next_uniform(state)
        cos1 = 2.0 * u - 1.0
        return state, 0.5 * etot, cos1, etot - 0.5 * etot, -cos1
    zeta_min = 1.0 / (gamma + 1.0 + p)
    ln_ratio = math.log(gamma + p)  # ln((1 − ζ_min)/ζ_min)
    a = (gamma + 1.0) * (gamma + 1.0)
    b = gamma * gamma + 4.0 * gamma + 1.0
    bound = gamma * gamma + 2.0 * gamma - 1.0  # max of ζ S(ζ), at ζ = 1/(γ + 1)
    while True:
        state, u1 = next_uniform(state)
        state, u2 = next_uniform(state)
        zeta = zeta_min * math.exp(u1 * ln_ratio)
        if u2 * bound <= b - a * zeta - 1.0 / zeta:
            break
    k1 = zeta * etot
    k2 = etot - k1
    cos1 = (gamma + 1.0 - etot / k1) / p
    cos2 = (gamma + 1.0 - etot / k2) / p
    return state, k1, min(max(cos1, -1.0), 1.0), k2, min(max(cos2, -1.0), 1.0)


@kernel
def wentzel_mean(a):
    """⟨1 − μ⟩ = 2A[(1 + A) ln(1 + 1/A) − 1] of p(μ) ∝ (1 − μ + 2A)⁻² on [−1, 1]."""
    return 2.0 * a * ((1.0 + a) * math.log1p(1.0 / a) - 1.0)


def _screening_table() -> np.ndarray:
    """ln A on the logit nodes of :data:`_LOGIT_MIN` + k·:data:`_LOGIT_STEP` (numpy, at import):
    the Newton iteration of :func:`wentzel_screening` from its safe start, run to convergence."""
    t = _LOGIT_MIN + _LOGIT_STEP * np.arange(_N_SCREEN)
    m1 = 1.0 / (1.0 + np.exp(-t))
    a = 0.5 * m1 / (np.log(1.0 / m1) + 2.0)
    for _ in range(200):
        el = np.log1p(1.0 / a)
        g = 2.0 * a * ((1.0 + a) * el - 1.0)
        step = (np.log(m1) - np.log(g)) * g / (a * (2.0 * (1.0 + 2.0 * a) * el - 4.0))
        a = a * np.exp(step)
        if np.abs(step).max() < 1e-12:
            break
    return np.log(a)


#: Logit nodes t = ln(m1/(1 − m1)) of the screening table (ln A is smooth in t at both ends:
#: ≈ ln m1 − ln ln(1/m1) for small m1, ≈ t − ln 3 as m1 → 1).
_LOGIT_MIN, _LOGIT_STEP, _N_SCREEN = -25.0, 0.004, 10501
_LN_SCREENING = _screening_table()


@kernel
def wentzel_screening(m1):
    """A > 0 with ⟨1 − μ⟩ = m1 ∈ (0, 1): Newton's method on ln⟨1 − μ⟩ against ln A.

    ln⟨1 − μ⟩ is increasing and concave in ln A, so Newton from a start below the root climbs
    to it without overshoot; the start 0.5·m1/(ln(1/m1) + 2) is below the root for every m1.
    Inside the table (m1 from 1.4e-11 to 1 − 5e-8) the start is ln A interpolated linearly in
    the logit of m1 (relative error ≲ 1e-7) and one Newton step (quadratic convergence) ends
    it, instead of up to a dozen from the safe start (one call per electron step: 0.5 µs →
    ~0.1 µs).
    """
    return screening_from_logs(math.log(m1), math.log(m1 / (1.0 - m1)))


@kernel
def screening_from_logs(ln_m1, logit_m1):
    """:func:`wentzel_screening` of m1 given ln m1 and ln(m1/(1 − m1)) (a caller that knows
    them, as :func:`sample_ms_cos` does, saves the logarithms)."""
    y = (logit_m1 - _LOGIT_MIN) / _LOGIT_STEP
    if 0.0 <= y < _N_SCREEN - 1:
        i = int(y)
        lo = _LN_SCREENING[i]
        a = math.exp(lo + (y - i) * (_LN_SCREENING[i + 1] - lo))
        return _newton_screening_step(a, ln_m1)[0]  # ≲ 1e-7 → ≲ 1e-12
    m1 = math.exp(ln_m1)
    a = 0.5 * m1 / (-ln_m1 + 2.0)
    for _ in range(100):
        a, step = _newton_screening_step(a, ln_m1)
        if abs(step) < 1e-12:
            break
    return a


@kernel
def _newton_screening_step(a, target):
    """One Newton step on ln⟨1 − μ⟩(A) = ``target`` in ln A: (A, Δ ln A), with
    ⟨1 − μ⟩ = 2A[(1 + A)L − 1] and d⟨1 − μ⟩/dA = 2(1 + 2A)L − 4, L = ln(1 + 1/A)."""
    el = math.log1p(1.0 / a)
    g = 2.0 * a * ((1.0 + a) * el - 1.0)
    dg = 2.0 * (1.0 + 2.0 * a) * el - 4.0
    step = (target - math.log(g)) * g / (a * dg)  # Δ ln A = Δ ln g / (d ln g / d ln A)
    return a * math.exp(step), step


@kernel
def wentzel_second(a):
    """⟨(1 − μ)²⟩ = 2A(1 + A)[2 + 2A − 2A²/(1 + A) − 4A ln(1 + 1/A)] of p(μ) ∝ (1 − μ + 2A)⁻²."""
    return 2.0 * a * (1.0 + a) * (2.0 + 2.0 * a - 2.0 * a * a / (1.0 + a)
                                  - 4.0 * a * math.log1p(1.0 / a))


@kernel
def lambda2_inverse(et, m, sp, e):
    """Second transport mass cross section 1/λ₂ [cm²/g] at e [MeV]."""
    i, f = electron_position(et, e)
    return (1.0 - f) * et.lambda2_inv[m, sp, i] + f * et.lambda2_inv[m, sp, i + 1]


@kernel
def sample_ms_cos(et, m, sp, e, s_g_cm2, state):
    """Polar deflection cos θ after a step of mass thickness s_g_cm2 [g/cm²] at energy e [MeV].

    Wentzel shape mixed with a fixed deflection so that ⟨1 − μ⟩ = 1 − exp(−s/λ₁) and
    ⟨P₂(μ)⟩ = exp(−s/λ₂) exactly (module docstring); isotropic for s/λ₁ > ln 1e6;
    cos θ = 1 for s ≤ 0.
    """
    i, f = electron_position(et, e)
    x = s_g_cm2 * ((1.0 - f) * et.lambda1_inv[m, sp, i] + f * et.lambda1_inv[m, sp, i + 1])
    if not x > 0.0:
        return state, 1.0
    state, u = next_uniform(state)
    if x > _ISOTROPIC_X:
        return state, 2.0 * u - 1.0
    g1 = -math.expm1(-x)
    ln_g1 = math.log(g1)
    a = screening_from_logs(ln_g1, ln_g1 + x)  # 1 − G₁ = e^(−x)
    l2 = (1.0 - f) * et.lambda2_inv[m, sp, i] + f * et.lambda2_inv[m, sp, i + 1]
    t2 = (3.0 * g1 + math.expm1(-s_g_cm2 * l2)) / 1.5
    m2 = wentzel_second(a)
    if t2 < m2:
        b = (m2 - t2) / (m2 - g1 * g1)
        if u < b:
            return state, 1.0 - g1
        u = (u - b) / (1.0 - b)
    return state, 1.0 - 2.0 * a * u / (1.0 + a - u)
