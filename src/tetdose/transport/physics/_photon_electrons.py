"""Electrons and positrons that photons set in motion (dose mode): kinematics and angular samplers.

- **Compton recoil electron** (free electron at rest, the Klein–Nishina event of
  :func:`~._photon.sample_klein_nishina`): kinetic energy T = E − E', momentum
  p_e = E·d − E'·d' (photon momenta in MeV/c), so its direction is that vector normalised
  (:func:`compton_electron_direction`). Exact for the free-electron model.
- **Photo-electron**: T = E (the shell's binding energy, < 1 keV in soft tissue and 4 keV for
  calcium's K shell, travels with the electron instead of being emitted as fluorescence or Auger
  electrons at the atom: a displacement of at most a few µm); direction from the **Sauter (1931)**
  K-shell distribution (:func:`sample_sauter_cos`), the model EGSnrc and PENELOPE use:

      dσ/dΩ ∝ sin²θ / (1 − β cos θ)⁴ · [1 + ½ γ(γ − 1)(γ − 2)(1 − β cos θ)]

  (F. Sauter, Ann. Phys. 403:454, 1931; the form of the PENELOPE-2018 manual, photoelectric
  effect, with its A = 1/β − 1 written out).
- **Pair production**: T₋ + T₊ = E − 2mc², shared uniformly (the same rule
  :mod:`tetdose.transport.physics.xs` uses for μen); each particle's polar angle from the leading
  term of the high-energy angular distribution, p(cos θ) ∝ (1 − β cos θ)⁻² (EGSnrc's default
  "simple" pair angular sampling, Kawrakow et al., NRCC Report PIRS-701; typical angle mc²/E), the two at
  opposite azimuths (:func:`sample_leading_term_cos`).
"""

import math

from tetdose._jit import kernel
from tetdose._random import next_uniform

#: Electron rest energy [MeV] (CODATA 2018).
ELECTRON_MASS_MEV = 0.51099895


@kernel
def compton_electron_direction(e_mev, e_out_mev, u, v, w, u2, v2, w2):
    """Unit direction of the Compton electron, p_e = E·(u, v, w) − E'·(u2, v2, w2) normalised
    (the photon's direction if that vector vanishes to round-off)."""
    px = e_mev * u - e_out_mev * u2
    py = e_mev * v - e_out_mev * v2
    pz = e_mev * w - e_out_mev * w2
    norm = math.sqrt(px * px + py * py + pz * pz)
    if norm <= 1e-300:
        return u, v, w
    return px / norm, py / norm, pz / norm


@kernel
def _beta_gamma(t_mev):
    """(β, γ, 1 − β) of an electron of kinetic energy T [MeV]; 1 − β = γ⁻²/(1 + β) without
    cancellation."""
    gamma = 1.0 + t_mev / ELECTRON_MASS_MEV
    inv_g2 = 1.0 / (gamma * gamma)
    beta = math.sqrt(max(1.0 - inv_g2, 0.0))
    return beta, gamma, inv_g2 / (1.0 + beta)


@kernel
def sample_sauter_cos(t_mev, state):
    """(state, cos θ) of a K-shell photo-electron of kinetic energy T [MeV] (Sauter, see module).

    With t = 1 − β cos θ ∈ [a, b] = [1 − β, 1 + β] the density is
    ∝ (t − a)(b − t)·(1 + c t)/t⁴, c = ½γ(γ − 1)(γ − 2). Proposal ∝ t⁻³ (inverted:
    t = (a⁻² − ξ(a⁻² − b⁻²))^(−1/2)); the ratio (t − a)(b − t)(1 + c t)/t is bounded by
    (a + b − 2√(ab))·max(1 + c a, 1 + c b) = (2 − 2/γ)·max(…) (the first factor's maximum, at
    t = √(ab) = 1/γ), so the rejection is exact.
    """
    beta, gamma, a = _beta_gamma(t_mev)
    if beta < 1e-6:
        state, xi = next_uniform(state)
        return state, 2.0 * xi - 1.0
    b = 1.0 + beta
    c = 0.5 * gamma * (gamma - 1.0) * (gamma - 2.0)
    bound = (2.0 - 2.0 / gamma) * max(1.0 + c * a, 1.0 + c * b)
    ia2 = 1.0 / (a * a)
    span = ia2 - 1.0 / (b * b)
    while True:
        state, x1 = next_uniform(state)
        state, x2 = next_uniform(state)
        t = 1.0 / math.sqrt(ia2 - x1 * span)
        if x2 * bound <= (t - a) * (b - t) * (1.0 + c * t) / t:
            return state, min(max((1.0 - t) / beta, -1.0), 1.0)


@kernel
def sample_leading_term_cos(t_mev, state):
    """(state, cos θ) from p(cos θ) ∝ (1 − β cos θ)⁻² (pair e±, see module), inverted exactly:
    cos θ = (2ξ − 1 + β)/(1 − β + 2βξ)."""
    beta, _gamma, one_minus_beta = _beta_gamma(t_mev)
    state, xi = next_uniform(state)
    return state, (2.0 * xi - one_minus_beta) / (one_minus_beta + 2.0 * beta * xi)
