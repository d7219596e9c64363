"""Photon interaction kernels: table lookup, Klein–Nishina sampling, one interaction.

Physics model (collision kerma: every charged particle deposits its kinetic energy where it is
set in motion):

- photoelectric absorption: the whole photon energy is deposited locally (fluorescence is not
  followed; for tissue the K-shell fluorescence energy is < 1 keV);
- incoherent scattering: Klein–Nishina on a free electron at rest, sampled by the
  Butcher & Messel (1960) / Kahn mixture method as used in EGS4 (Nelson et al., SLAC-265,
  §2.9); the electron's kinetic energy E − E' is deposited locally;
- pair production (nuclear and electron field): E − 2mc² deposited locally, two photons of mc²
  emitted back to back in an isotropic direction (positron annihilation at rest);
- coherent (Rayleigh) scattering is **not transported**: it changes no energy, its angular
  distribution needs atomic form factors that mucoeff does not carry, and it deflects photons
  by small angles. It is left out consistently: :func:`transport_coefficients` and
  :func:`interact` use μ_t = μ_incoh + μ_photo + μ_pair. :func:`lookup` still returns it.

Interpolation (grid position: one ln E per call). :func:`lookup` interpolates each process
log–log, ``a·exp(f·ln(b/a))``. The transport kernels read the precomputed tables of
:class:`tetdose.transport.physics.xs.CrossSections`: :func:`transport_coefficients` interpolates ln μ_t and
ln μen linearly in ln E, ``exp(ln a + f·(ln b − ln a))`` (log–log interpolation of the total:
two exp per call); :func:`interact` chooses the process from the branching fractions
μ_incoh/μ_t and μ_pair/μ_t interpolated linearly in ln E (no transcendental function).

Process codes are the table indices of :class:`tetdose.transport.physics.xs.CrossSections`.
"""

import math

from numba import njit

from tetdose._jit import kernel
from tetdose._random import next_uniform

COHERENT = 0
INCOHERENT = 1
PHOTOELECTRIC = 2
PAIR = 3
#: Electron rest energy [MeV] (CODATA 2018); 2mc² is the pair threshold.
ELECTRON_MASS_MEV = 0.51099895
_TWO_PI = 2.0 * math.pi


@njit(cache=True, inline="always")
def _loglog(a, b, f):
    """Interpolate between node values a, b at fraction f of the ln(E) interval (log–log)."""
    if a > 0.0 and b > 0.0:
        return a * math.exp(f * math.log(b / a))
    return a + f * (b - a)


@njit(cache=True, inline="always")
def grid_position(xs, energy_mev):
    """(i, f): E lies at fraction f of the ln(E) interval [E_i, E_i+1], clamped to the grid."""
    n = xs.mu_rho_cm2_g.shape[1]
    x = (math.log(energy_mev) - xs.ln_e_min) / xs.d_ln_e
    i = min(max(int(math.floor(x)), 0), n - 2)
    return i, min(max(x - i, 0.0), 1.0)


@njit(cache=True, inline="always")
def _lerp(table, material, i, f):
    """table[material, i] + f·(table[material, i+1] − table[material, i]) (linear in ln E)."""
    a = table[material, i]
    return a + f * (table[material, i + 1] - a)


@njit(cache=True, inline="always")
def _mu(xs, material, i, f, process):
    table = xs.mu_rho_cm2_g
    return _loglog(table[material, i, process], table[material, i + 1, process], f)


@njit(cache=True, inline="always")
def _transported(xs, material, energy_mev, i, f):
    """(incoherent, photoelectric, pair) [cm²/g]; pair exactly 0 below 2mc²."""
    pair = 0.0
    if energy_mev > 2.0 * ELECTRON_MASS_MEV:
        pair = _mu(xs, material, i, f, PAIR)
    return _mu(xs, material, i, f, INCOHERENT), _mu(xs, material, i, f, PHOTOELECTRIC), pair


@kernel
def lookup(xs, material, energy_mev):
    """(coherent, incoherent, photoelectric, pair, mu_en) mass coefficients [cm²/g] at E [MeV].

    Log–log interpolation between the two ln(E) grid nodes around E; E outside the grid takes
    the end value. Pair is exactly 0 below 2mc² = 1.022 MeV.
    """
    i, f = grid_position(xs, energy_mev)
    inc, pe, pair = _transported(xs, material, energy_mev, i, f)
    en = xs.mu_en_rho_cm2_g
    mu_en = _loglog(en[material, i], en[material, i + 1], f)
    return _mu(xs, material, i, f, COHERENT), inc, pe, pair, mu_en


@kernel
def transport_coefficients(xs, material, energy_mev):
    """(μ_t/ρ transported = incoherent + photoelectric + pair, μen/ρ), both [cm²/g] at E [MeV].

    μ_t = exp(ln μ_t,i + f·(ln μ_t,i+1 − ln μ_t,i)), the same for μen: log–log interpolation of
    the totals. It agrees with the sum of :func:`lookup`'s per-process values to the
    interpolation error (< 1e-4 relative). Only in the grid interval that contains 2mc² does
    the pair part of the upper node (< 3e-6 of μ_t) reach energies below the threshold.
    """
    i, f = grid_position(xs, energy_mev)
    return (math.exp(_lerp(xs.ln_mu_transported, material, i, f)),
            math.exp(_lerp(xs.ln_mu_en, material, i, f)))


@njit(cache=True, inline="always")
def mu_transported_at(xs, material, i, f):
    """μ_t/ρ [cm²/g] at grid position (i, f) of :func:`grid_position` (the first value of
    :func:`transport_coefficients`, bit for bit, for a caller that keeps (i, f) for one E)."""
    return math.exp(_lerp(xs.ln_mu_transported, material, i, f))


@njit(cache=True, inline="always")
def majorant_at(ln_mu_hat, i, f):
    """μ̂ [1/cm] at grid position (i, f) of a majorant table ln μ̂ [ln 1/cm] on the nodes of the
    cross sections (linear in ln E, as :func:`transport_coefficients`)."""
    a = ln_mu_hat[i]
    return math.exp(a + f * (ln_mu_hat[i + 1] - a))


@kernel
def branching_fractions(xs, material, energy_mev):
    """(μ_incoh/μ_t, μ_pair/μ_t) at E [MeV], interpolated linearly in ln E as :func:`interact`
    does (dose mode chooses its process with them, :mod:`tetdose.transport.history._coupled`)."""
    i, f = grid_position(xs, energy_mev)
    return _lerp(xs.p_incoherent, material, i, f), _lerp(xs.p_pair, material, i, f)


@kernel
def sample_klein_nishina(energy_mev, state):
    """Sample a Compton scatter on a free electron: (state, E' [MeV], cos θ).

    ε = E'/E ∈ [ε₀, 1], ε₀ = 1/(1+2k), k = E/mc². dσ/dε ∝ (1/ε + ε)·g(ε) with
    g = 1 − ε sin²θ/(1+ε²) ≤ 1. Choose 1/ε (weight α₁ = ln(1/ε₀)) or ε (weight
    α₂ = (1−ε₀²)/2), sample ε from it, accept with probability g (EGS4, SLAC-265 §2.9).
    """
    k = energy_mev / ELECTRON_MASS_MEV
    eps0 = 1.0 / (1.0 + 2.0 * k)
    eps0_sq = eps0 * eps0
    alpha1 = -math.log(eps0)
    p1 = alpha1 / (alpha1 + 0.5 * (1.0 - eps0_sq))
    while True:
        state, r1 = next_uniform(state)
        state, r2 = next_uniform(state)
        state, r3 = next_uniform(state)
        if r1 < p1:
            eps = math.exp(-alpha1 * r2)
        else:
            eps = math.sqrt(eps0_sq + (1.0 - eps0_sq) * r2)
        t = (1.0 - eps) / (k * eps)  # 1 − cos θ
        sin_sq = t * (2.0 - t)
        if r3 <= 1.0 - eps * sin_sq / (1.0 + eps * eps):
            return state, eps * energy_mev, 1.0 - t


@kernel
def _kn_column(x, eps0, k):
    """G(x) − G(ε₀) of :func:`klein_nishina_inverse`, written in differences (no cancellation
    of the 1/k² terms at small k)."""
    d = x - eps0
    lg = math.log(x / eps0)
    return (lg + 0.5 * d * (x + eps0) - 2.0 * (lg - d) / k
            + ((1.0 / eps0 - 1.0 / x) - 2.0 * lg + d) / (k * k))


@kernel
def klein_nishina_inverse(energy_mev, xi):
    """Compton scatter on a free electron by inversion of the Klein–Nishina CDF: (E' [MeV],
    cos θ) with ε = E'/E the root of G(ε) − G(ε₀) = ξ·(G(1) − G(ε₀)),

        G(x) = ln x + x²/2 − (2/k)(ln x − x) + (1/k²)(−1/x − 2 ln x + x),

    the integral of dσ/dε ∝ 1/ε + ε − sin²θ (sin²θ = 2t − t², t = (1/ε − 1)/k = 1 − cos θ), the
    distribution :func:`sample_klein_nishina` draws by rejection; monotone in ξ, so stratified
    or quasi-random ξ stratify the scattered energy. Safeguarded Newton on [ε₀, 1]."""
    k = energy_mev / ELECTRON_MASS_MEV
    eps0 = 1.0 / (1.0 + 2.0 * k)
    target = xi * _kn_column(1.0, eps0, k)
    lo, hi = eps0, 1.0
    x = eps0 + xi * (1.0 - eps0)
    for _ in range(60):
        g = _kn_column(x, eps0, k) - target
        if g > 0.0:
            hi = x
        else:
            lo = x
        t = (1.0 / x - 1.0) / k
        dg = 1.0 / x + x - t * (2.0 - t)
        step = g / dg
        x_new = x - step
        if not lo < x_new < hi:
            x_new = 0.5 * (lo + hi)
        if abs(x_new - x) <= 1e-14 * x:
            x = x_new
            break
        x = x_new
    t = (1.0 / x - 1.0) / k
    return x * energy_mev, 1.0 - t


@kernel
def rotate_direction(u, v, w, cos_theta, phi):
    """Unit vector at polar angle θ (cos θ given) and azimuth φ [rad] about (u, v, w)
    (:func:`rotate_cs`)."""
    return rotate_cs(u, v, w, cos_theta, math.cos(phi), math.sin(phi))


@njit(cache=True, inline="always")
def rotate_cs(u, v, w, cos_theta, cos_phi, sin_phi):
    """Unit vector at polar angle θ (cos θ given) and azimuth φ (cos φ, sin φ given) about
    (u, v, w).

    Standard rotation (e.g. PENELOPE-2018 manual eq. 1.131); the |w| → 1 limit is handled
    separately. The result is renormalised against round-off.
    """
    cos_theta = min(max(cos_theta, -1.0), 1.0)
    sin_theta = math.sqrt(max(0.0, 1.0 - cos_theta * cos_theta))
    s = 1.0 - w * w
    if s > 1e-12:
        root = math.sqrt(s)
        u2 = u * cos_theta + sin_theta * (u * w * cos_phi - v * sin_phi) / root
        v2 = v * cos_theta + sin_theta * (v * w * cos_phi + u * sin_phi) / root
        w2 = w * cos_theta - root * sin_theta * cos_phi
    else:
        sign = 1.0 if w > 0.0 else -1.0
        u2 = sin_theta * cos_phi
        v2 = sin_theta * sin_phi
        w2 = sign * cos_theta
    norm = 1.0 / math.sqrt(u2 * u2 + v2 * v2 + w2 * w2)
    return u2 * norm, v2 * norm, w2 * norm


@kernel
def isotropic_direction(state):
    """(state, u, v, w): a direction uniform on the unit sphere (cos θ uniform in [−1, 1])."""
    state, r1 = next_uniform(state)
    state, r2 = next_uniform(state)
    w = 2.0 * r1 - 1.0
    s = math.sqrt(max(0.0, 1.0 - w * w))
    phi = _TWO_PI * r2
    return state, s * math.cos(phi), s * math.sin(phi), w


@kernel
def interact(xs, material, energy_mev, u, v, w, state):
    """Sample and apply one interaction of a photon of E [MeV] moving along (u, v, w).

    The process is chosen with probability μ_p/μ_t, μ_t = μ_incoh + μ_photo + μ_pair (coherent
    left out, see the module docstring), from the branching fractions interpolated linearly in
    ln E: incoherent if ξ < p_incoh, else pair if ξ < p_incoh + p_pair and E > 2mc² (never at
    or below the threshold; the < 3e-6 pair fraction interpolated there goes to photoelectric),
    else photoelectric. Returns ``(state, process, deposited_mev, energy_out_mev,
    u2, v2, w2, secondary_energy_mev, su, sv, sw)``: the continuing photon (energy 0 when
    absorbed) and a secondary photon (energy 0 when none, pair only). Energy balance:
    deposited + energy_out + secondary = E.
    """
    i, f = grid_position(xs, energy_mev)
    p_incoherent = _lerp(xs.p_incoherent, material, i, f)
    state, r = next_uniform(state)
    if r < p_incoherent:
        state, e_out, cos_theta = sample_klein_nishina(energy_mev, state)
        state, r_phi = next_uniform(state)
        u2, v2, w2 = rotate_direction(u, v, w, cos_theta, _TWO_PI * r_phi)
        return (state, INCOHERENT, energy_mev - e_out, e_out, u2, v2, w2,
                0.0, 0.0, 0.0, 0.0)
    if r < p_incoherent + _lerp(xs.p_pair, material, i, f) and energy_mev > 2.0 * ELECTRON_MASS_MEV:
        state, u2, v2, w2 = isotropic_direction(state)
        return (state, PAIR, energy_mev - 2.0 * ELECTRON_MASS_MEV, ELECTRON_MASS_MEV,
                u2, v2, w2, ELECTRON_MASS_MEV, -u2, -v2, -w2)
    return state, PHOTOELECTRIC, energy_mev, 0.0, u, v, w, 0.0, 0.0, 0.0, 0.0
