"""Built-in breathing motion: the Lujan cos²ⁿ time course on a field that keeps tissue volume.

Time course (Lujan, Larsen, Balter & Ten Haken, Med. Phys. 26(5) 715–720, 1999):

    z(t) = z₀ − b · cos²ⁿ(π t / τ − φ),

z₀ the end-exhale position, b the amplitude [mm], τ the period [s], n the shape (n = 1
sinusoidal; n = 2–3 typical: longer rest at exhale), φ the phase offset [rad]. With φ = 0 the
cycle starts at end-inhale (phase 0 %, the 4D-CT convention) and reaches end-exhale at 50 %.

The **reference mesh is the end-exhale state** (s = 0). At s(t) = cos²ⁿ(π t/τ − φ) ∈ [0, 1]
a reference point p = (x, y, z) moves to χ_s(p). With ζ = (z_max − z)/H ∈ [0, 1] (H the mesh's
cranio-caudal extent; 0 at the apex, 1 at the inferior end, the diaphragm) and c its box
centre, **all tissue but lung moves incompressibly** (liver, tumour, soft tissue keep their
volume; lungs are the organ whose volume breathes):

    z' = z − s·b·ζ²,   (x', y') = c_xy + (x − c_x, y − c_y) / √J,   J = ∂z'/∂z = 1 + 2sbζ/H,

so the cranio-caudal stretch J is balanced by a lateral/anteroposterior contraction and
det ∂χ/∂p = J · (1/√J)² = 1 at every point (∂x'/∂y = ∂y'/∂x = ∂z'/∂x = ∂z'/∂y = 0: the
Jacobian is triangular). On tetrahedra (vertex positions linear inside each) the volume of a
tet changes only by the curvature of χ across it, O((b/H)·(edge/H)) — well under 1 % for
edges of a few mm.

**Lung** (``lung_regions``; default: the regions whose mean reference density is below
:data:`LUNG_DENSITY_G_CM3`, so a mapped mesh finds its lungs itself) expands on inhale as well:
there the lateral/anteroposterior motion is the expansion x' = x + s·b·ζ²·r_LR·ξ_x (ξ the
position over the box half-width; r_LR = 0.15, r_AP = 0.3 after Seppenwoolde et al., IJROBP 53,
2002) with the same cranio-caudal motion, so lung volume grows by ≈ ∫(2sbζ/H + sbζ²(r_LR/h_x +
r_AP/h_y)). Lung vertices within :data:`BLEND_MM` of other tissue blend smoothly into the
incompressible motion (smoothstep of the distance), so every vertex of a non-lung tetrahedron
moves incompressibly and the two motions meet without folding. A mesh without lung is moved
incompressibly as a whole. The per-region volume change of every phase is reported by
:func:`tetdose.motion.conserve.update_series`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from tetdose._typing import FloatArray, IntArray
from tetdose.core.mesh import TetMesh
from tetdose.errors import TetdoseError
from tetdose.motion.phases import DENSITY, PhaseSeries

#: A region whose volume-weighted mean reference density is below this [g/cm³] is lung.
LUNG_DENSITY_G_CM3 = 0.5
#: Distance [mm] over which lung motion blends into the incompressible motion of other tissue.
BLEND_MM = 20.0


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

    def incompressible_points(self, points_mm: FloatArray, box_mm: tuple[FloatArray, FloatArray],
                              s: float) -> FloatArray:
        """χ_s(p) (P, 3) [mm] of the volume-keeping motion (module docstring), det ∂χ/∂p = 1."""
        lo, hi = (np.asarray(b, dtype=np.float64) for b in box_mm)
        height = max(hi[2] - lo[2], 1e-12)
        zeta = (hi[2] - points_mm[:, 2]) / height
        stretch = 1.0 + 2.0 * s * self.amplitude_mm * zeta / height
        centre = 0.5 * (lo + hi)
        out = points_mm.copy()
        out[:, :2] = centre[:2] + (points_mm[:, :2] - centre[:2]) / np.sqrt(stretch)[:, None]
        out[:, 2] -= s * self.amplitude_mm * zeta**2
        return out

    def lung_points(self, points_mm: FloatArray, box_mm: tuple[FloatArray, FloatArray],
                    s: float) -> FloatArray:
        """Positions (P, 3) [mm] under the expanding lung motion (module docstring)."""
        lo, hi = (np.asarray(b, dtype=np.float64) for b in box_mm)
        half = np.maximum(0.5 * (hi - lo), 1e-12)
        xi = (points_mm - 0.5 * (lo + hi)) / half
        w = s * self.amplitude_mm * ((hi[2] - points_mm[:, 2]) / (2.0 * half[2])) ** 2
        return points_mm + np.stack([w * self.lr_ratio * xi[:, 0], w * self.ap_ratio * xi[:, 1],
                                     -w], axis=1)

    def points_at(self, reference: TetMesh, t_s: float, *,
                  lung_regions: Sequence[int] | None = None,
                  density_g_cm3: FloatArray | None = None) -> FloatArray:
        """Vertex positions (N, 3) [mm] at time ``t_s`` (the field is set on the mesh's box)."""
        weight = self.lung_weight(reference, lung_regions, density_g_cm3)
        return self._points(reference, float(self.cycle(t_s)), weight)

    def _points(self, reference: TetMesh, s: float, weight: FloatArray) -> FloatArray:
        box = reference.bounds_mm()
        p = self.incompressible_points(reference.points_mm, box, s)
        if weight.any():
            p += weight[:, None] * (self.lung_points(reference.points_mm, box, s) - p)
        return p

    @staticmethod
    def lung_weight(reference: TetMesh, lung_regions: Sequence[int] | None = None,
                    density_g_cm3: FloatArray | None = None) -> FloatArray:
        """Per-vertex weight (N,) ∈ [0, 1] of the lung motion: 0 at every vertex of a non-lung
        tet, rising to 1 (smoothstep) at :data:`BLEND_MM` from them inside lung."""
        lung = lung_tets(reference, lung_regions, density_g_cm3)
        weight = np.zeros(reference.n_points)
        if not lung.any():
            return weight
        in_lung = np.zeros(reference.n_points, dtype=bool)
        in_lung[reference.tets[lung].ravel()] = True
        other = np.zeros(reference.n_points, dtype=bool)
        other[reference.tets[~lung].ravel()] = True
        if not other.any():
            return in_lung.astype(np.float64)
        from scipy.spatial import cKDTree

        free = in_lung & ~other
        dist, _ = cKDTree(reference.points_mm[other]).query(reference.points_mm[free])
        t = np.clip(dist / BLEND_MM, 0.0, 1.0)
        weight[free] = t * t * (3.0 - 2.0 * t)
        return weight

    def series(self, reference: TetMesh, n_phases: int = 10, *,
               lung_regions: Sequence[int] | None = None,
               density_g_cm3: FloatArray | None = None) -> PhaseSeries:
        """K phases at t_k = k τ/K (phase 100·k/K %), equal time weights 1/K.

        ``lung_regions``: region labels that are lung (default: found from the reference
        density, ``density_g_cm3`` or the mesh's point_data, :func:`lung_tets`).
        """
        if n_phases < 1:
            raise TetdoseError(f"need at least one phase, got {n_phases}")
        weight = self.lung_weight(reference, lung_regions, density_g_cm3)
        t = self.period_s * np.arange(n_phases) / n_phases
        pts = np.stack([self._points(reference, float(self.cycle(ti)), weight) for ti in t])
        return PhaseSeries(reference, pts, 100.0 * np.arange(n_phases) / n_phases)


def lung_tets(reference: TetMesh, lung_regions: Sequence[int] | None = None,
              density_g_cm3: FloatArray | None = None) -> np.ndarray:
    """Boolean (M,): the tetrahedra that are lung.

    Given ``lung_regions``, the tets of those region labels (an unknown label is refused).
    Otherwise every region (the whole mesh if unlabelled) whose volume-weighted mean vertex
    density is below :data:`LUNG_DENSITY_G_CM3`; without any density, no lung.
    """
    region = (np.zeros(reference.n_tets, dtype=np.int64) if reference.region is None
              else reference.region)
    if lung_regions is not None:
        wanted = np.asarray(list(lung_regions), dtype=np.int64)
        missing = np.setdiff1d(wanted, region)
        if missing.size:
            raise TetdoseError(f"lung region(s) {missing.tolist()} not in the mesh (its regions: "
                               f"{np.unique(region).tolist()}); give labels the mesh has")
        return np.isin(region, wanted)
    rho = density_g_cm3
    if rho is None and DENSITY in reference.point_data:
        rho = reference.point_data[DENSITY]
    if rho is None:
        return np.zeros(reference.n_tets, dtype=bool)
    tet_rho = np.asarray(rho, dtype=np.float64).reshape(-1)[reference.tets].mean(axis=1)
    labels, inverse = np.unique(region, return_inverse=True)
    vol = reference.volumes_mm3
    mean = np.bincount(inverse, vol * tet_rho) / np.bincount(inverse, vol)
    lung_labels: IntArray = labels[mean < LUNG_DENSITY_G_CM3]
    return np.isin(region, lung_labels)
