"""Where kerma ≠ dose, measured: one world and one plan run twice — with electrons (absorbed dose,
``physics="dose"``) and without (collision kerma, ``physics="kerma"``) — on the same random streams.

*Per structure* (:func:`structure_ratios`), over its voxels in the fields (kerma ≥ 20 % of the
maximum): the mass-weighted mean dose over the mean kerma, and the mass fraction where the dose
lies more than 5 % below the kerma by more than 2 σ of the ratio (σ from both runs' batch
statistics) — the build-up region under the skin, lung
near small fields, field edges: measured, not estimated from a d_max table.

*Per beam* (:func:`beam_axis_profiles`): each beam alone, dose and kerma along its central axis
from 20 mm before the skin entry to 50 mm past the isocentre (trilinear samples of the combined
voxel images, averaged over a 10 × 10 mm² square across the axis), depth measured from the skin
entry, where the density along the axis first reaches
:data:`SKIN_G_CM3`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from tetdose._typing import BoolArray, FloatArray
from tetdose.compare.profiles import image_profile
from tetdose.compare.report import Figure, pyplot, render_png
from tetdose.core.image import Image
from tetdose.core.transfer import interpolate_at_points
from tetdose.plan.model import Plan
from tetdose.transport import TransportSettings, World, simulate

#: Density [g/cm³] at which a beam's axis enters the body (the skin).
SKIN_G_CM3 = 0.5
#: Width [mm] of the square across each beam's axis over which its profile is averaged, and the
#: number of parallel lines per side.
AXIS_WIDTH_MM = 10.0
AXIS_LINES = 3
#: Voxels counted: kerma ≥ this fraction of the maximum kerma (in the fields) and some dose.
IN_FIELD = 0.2
#: A cell "differs" when D/K < 1 − this, by more than :data:`SIGNIFICANCE` σ.
RATIO_TOLERANCE = 0.05
SIGNIFICANCE = 2.0


@dataclass(frozen=True, eq=False)
class AxisProfile:
    """One beam's central axis: depth below the skin [mm] (negative: in air before it), dose and
    kerma with their σ [Gy per source particle]."""

    name: str
    depth_mm: FloatArray
    dose_gy: FloatArray
    dose_std_gy: FloatArray
    kerma_gy: FloatArray
    kerma_std_gy: FloatArray

    def ratio_at(self, depth_mm: float) -> float:
        """D/K at a depth [mm] (linear between samples)."""
        r = np.divide(self.dose_gy, self.kerma_gy, out=np.full_like(self.dose_gy, np.nan),
                      where=self.kerma_gy > 0)
        ok = np.isfinite(r)
        return float(np.interp(depth_mm, self.depth_mm[ok], r[ok]))


def skin_entry(density: Image, iso_mm: FloatArray, direction: FloatArray,
               step_mm: float = 0.5) -> FloatArray:
    """The first point [mm] along the ray that ends at ``iso_mm`` (travelling ``direction``)
    where the density reaches :data:`SKIN_G_CM3`, marching in from the grid's edge."""
    d = np.asarray(direction, float) / np.linalg.norm(direction)
    reach = float(np.linalg.norm(np.asarray(density.grid.size) * density.grid.spacing_mm))
    t = np.arange(-reach, 0.0 + step_mm, step_mm)
    pts = np.asarray(iso_mm, float) + t[:, None] * d
    rho = np.nan_to_num(interpolate_at_points(density, pts), nan=0.0)
    inside = np.nonzero(rho >= SKIN_G_CM3)[0]
    return pts[inside[0]] if inside.size else np.asarray(iso_mm, float)


def beam_axis_profiles(world: World, plan: Plan, settings: TransportSettings,
                       beams: Sequence[tuple[str, FloatArray, FloatArray]],
                       n: int = 200) -> list[AxisProfile]:
    """Dose and kerma along each beam's axis, each beam run alone (``plan.treatment_beams``
    in the order of ``beams`` = (name, isocentre [mm], direction of travel))."""
    out = []
    for beam, (name, iso, direction) in zip(plan.treatment_beams, beams, strict=True):
        alone = replace(plan, treatment_beams=(beam,), prescription=None, calibration=None)
        runs = {phys: simulate(world, alone, replace(settings, physics=phys, estimator=None,
                                                     target_uncertainty=None), progress=False)
                for phys in ("dose", "kerma")}
        d = np.asarray(direction, float) / np.linalg.norm(direction)
        skin = skin_entry(world.density, iso, d)
        a, b = skin - 20.0 * d, np.asarray(iso, float) + 50.0 * d
        prof = {phys: _averaged_profile(r, a, b, d, n) for phys, r in runs.items()}
        depth = np.linspace(0.0, float(np.linalg.norm(b - a)), n) - 20.0
        out.append(AxisProfile(name, depth, *prof["dose"], *prof["kerma"]))
    return out


def _averaged_profile(result: Any, a: FloatArray, b: FloatArray, d: FloatArray,  # noqa: ANN401
                      n: int) -> tuple[FloatArray, FloatArray]:
    """(mean dose, its σ) along a → b over :data:`AXIS_LINES` parallel lines spread over a
    square of side :data:`AXIS_WIDTH_MM` across the beam (the central axis of a finite detector:
    a single voxel line of a Monte Carlo dose is too noisy to read)."""
    img, std = result.to_images()
    e1 = np.cross(d, [1.0, 0.0, 0.0] if abs(d[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(d, e1)
    offsets = np.linspace(-AXIS_WIDTH_MM / 2, AXIS_WIDTH_MM / 2, AXIS_LINES)
    doses, vars_ = [], []
    for u in offsets:
        for v in offsets:
            shift = u * e1 + v * e2
            doses.append(image_profile(img, a + shift, b + shift, n).dose_gy)
            vars_.append(image_profile(std, a + shift, b + shift, n).dose_gy ** 2)
    k = len(doses)
    # neighbouring lines share voxels: σ of the mean taken as that of one line / √(k/4)
    return np.nanmean(doses, axis=0), np.sqrt(np.nanmean(vars_, axis=0) / max(k / 4.0, 1.0))


def structure_ratios(dose: Image, dose_std: Image, kerma: Image, kerma_std: Image,
                     mass_g: FloatArray, masks: Mapping[str, BoolArray]) -> dict[str, Any]:
    """Per structure: mass-weighted mean D/K and the mass fraction where D/K < 1 − 5 % by more
    than 2 σ (module docstring); voxels of the combined images, ``mass_g`` per voxel."""
    d, k = np.asarray(dose.array, float).ravel(), np.asarray(kerma.array, float).ravel()
    sd, sk = np.asarray(dose_std.array, float).ravel(), np.asarray(kerma_std.array, float).ravel()
    m = np.asarray(mass_g, float).ravel()
    ratio = np.divide(d, k, out=np.ones_like(d), where=k > 0)
    sigma = ratio * np.sqrt(np.divide(sd, d, out=np.zeros_like(d), where=d > 0) ** 2
                            + np.divide(sk, k, out=np.zeros_like(k), where=k > 0) ** 2)
    below = (ratio < 1.0 - RATIO_TOLERANCE) & (1.0 - RATIO_TOLERANCE - ratio > SIGNIFICANCE * sigma)
    in_field = (k >= IN_FIELD * k.max()) & (d > 0)  # a voxel without a deposit has no σ
    out = {}
    for name, mask in masks.items():
        sel = np.asarray(mask, bool).ravel() & in_field
        if not sel.any():
            continue
        w = m[sel]
        out[name] = {"dose_over_kerma": float((d[sel] * w).sum() / (k[sel] * w).sum()),
                     "mass_fraction_dose_below_kerma": float(w[below[sel]].sum() / w.sum()),
                     "in_field_mass_g": float(w.sum())}
    return out


def dose_kerma_figure(profiles: Sequence[AxisProfile], *, unit: str) -> Figure:
    """One panel per beam: dose and kerma (±σ bands) along its axis vs depth below the skin."""
    plt = pyplot()
    fig, axes = plt.subplots(1, len(profiles), figsize=(4.5 * len(profiles), 3.8),
                             layout="constrained", squeeze=False)
    data: dict[str, Any] = {"unit": unit}
    for ax, p in zip(axes[0], profiles, strict=True):
        for label, y, s, style in (("dose (electrons)", p.dose_gy, p.dose_std_gy, "-"),
                                   ("kerma", p.kerma_gy, p.kerma_std_gy, "--")):
            ax.plot(p.depth_mm, y, style, label=label)
            ax.fill_between(p.depth_mm, y - s, y + s, alpha=0.25)
        ax.axvline(0.0, color="grey", lw=0.8)
        ax.set_title(f"{p.name}: D/K {p.ratio_at(2.0):.2f} at 2 mm, {p.ratio_at(5.0):.2f} at 5 mm",
                     fontsize=9)
        ax.set_xlabel("depth below the skin [mm]", fontsize=8)
        ax.set_ylabel(f"[{unit}]", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.legend(fontsize=7)
        data[p.name] = {"depth_mm": p.depth_mm, "dose_gy": p.dose_gy, "kerma_gy": p.kerma_gy,
                        "dose_std_gy": p.dose_std_gy, "kerma_std_gy": p.kerma_std_gy}
    fig.suptitle("Dose with electrons vs kerma along each beam's central axis (phase 0)",
                 fontsize=10)
    return Figure("dose_vs_kerma_beams", "Dose with electrons transported and collision kerma "
                  "along each beam's central axis from the skin (each beam alone, phase 0)",
                  render_png(fig), data)
