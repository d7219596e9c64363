"""Built-in breathing motion: the Lujan cos²ⁿ model with a smooth, volume-changing spatial field.

Time course (Lujan, Larsen, Balter & Ten Haken, Med. Phys. 26(5) 715–720, 1999):

    z(t) = z₀ − b · cos²ⁿ(π t / τ − φ),

z₀ the end-exhale position, b the amplitude [mm], τ the period [s], n the shape (n = 1
sinusoidal; n = 2–3 typical: longer rest at exhale), φ the phase offset [rad]. With φ = 0 the
cycle starts at end-inhale (phase 0 %, the 4D-CT convention) and reaches end-exhale at 50 %.

The **reference mesh is the end-exhale state** (s = 0). A vertex at reference position p moves
by u(p, t) = s(t) · U(p), s(t) = cos²ⁿ(π t/τ − φ) ∈ [0, 1], with

    U(p) = b · w(ζ) · (r_LR · ξ_x, r_AP · ξ_y, −1),   w(ζ) = ζ²,

ζ = (z_max − z)/(z_max − z_min) ∈ [0, 1] (0 at the apex, 1 at the inferior end, the
diaphragm: motion decays away from it), ξ = (x − x_c)/h the position relative to the box
centre over the half-width (lateral/anteroposterior expansion, smaller than the cranio-caudal
motion: r_LR = 0.15, r_AP = 0.3 by default, after Seppenwoolde et al., IJROBP 53, 2002).
z is the patient's superior axis (DICOM LPS: +z towards the head), so the inferior part moves
down on inhale. div U = b·(2ζ/H + w·(r_LR/h_x + r_AP/h_y)) ≥ 0: the volume grows on inhale.
U is a polynomial of p, hence smooth.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tetdose._typing import FloatArray
from tetdose.core.mesh import TetMesh
from tetdose.errors import TetdoseError
from tetdose.motion.phases import PhaseSeries


@dataclass(frozen=True)
class BreathingModel:
    """Lujan cos²ⁿ breathing: amplitude [mm], period [s], shape n, phase offset [rad]."""

    amplitude_mm: float = 10.0
    period_s: float = 4.0
    n: int = 3
    phase_offset_rad: float = 0.0
    ap_ratio: float = 0.3
    lr_ratio: float = 0.15

    def __post_init__(self) -> None:
        if not (self.amplitude_mm >= 0 and self.period_s > 0 and self.n >= 1):
            raise TetdoseError(
                f"breathing needs amplitude ≥ 0 mm, period > 0 s and n ≥ 1, got "
                f"{self.amplitude_mm} mm, {self.period_s} s, n = {self.n}"
            )

    def cycle(self, t_s: FloatArray | float) -> FloatArray:
        """s(t) = cos²ⁿ(π t/τ − φ) ∈ [0, 1]: 1 at end-inhale, 0 at end-exhale."""
        return np.cos(np.pi * np.asarray(t_s, dtype=np.float64) / self.period_s
                      - self.phase_offset_rad) ** (2 * self.n)

    def amplitude_field_mm(self, points_mm: FloatArray, box_mm: tuple[FloatArray, FloatArray]
                           ) -> FloatArray:
        """U(p) (P, 3) [mm]: the displacement at end-inhale of reference points."""
        lo, hi = (np.asarray(b, dtype=np.float64) for b in box_mm)
        half = np.maximum(0.5 * (hi - lo), 1e-12)
        xi = (points_mm - 0.5 * (lo + hi)) / half
        zeta = (hi[2] - points_mm[:, 2]) / (2.0 * half[2])
        w = self.amplitude_mm * zeta**2
        return np.stack([w * self.lr_ratio * xi[:, 0], w * self.ap_ratio * xi[:, 1], -w], axis=1)

    def points_at(self, reference: TetMesh, t_s: float) -> FloatArray:
        """Vertex positions (N, 3) [mm] at time ``t_s`` (the field is set on the mesh's box)."""
        u = self.amplitude_field_mm(reference.points_mm, reference.bounds_mm())
        return reference.points_mm + float(self.cycle(t_s)) * u

    def series(self, reference: TetMesh, n_phases: int = 10) -> PhaseSeries:
        """K phases at t_k = k τ/K (phase 100·k/K %), equal time weights 1/K."""
        if n_phases < 1:
            raise TetdoseError(f"need at least one phase, got {n_phases}")
        t = self.period_s * np.arange(n_phases) / n_phases
        pts = np.stack([self.points_at(reference, ti) for ti in t])
        return PhaseSeries(reference, pts, 100.0 * np.arange(n_phases) / n_phases)
