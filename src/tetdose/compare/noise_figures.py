"""Figures that show the noise: the normalised difference Δ/σ beside the difference, its histogram
against the unit Gaussian (Kawrakow & Fippel, Phys. Med. Biol. 45:2163, 2000, Fig. 6), and the
relative σ maps of both doses. Only the compared region is drawn (white outside: air and the
voxels the comparison leaves out)."""

from __future__ import annotations

from typing import Any

import numpy as np

from tetdose._typing import BoolArray, FloatArray
from tetdose.compare.report import Figure, pyplot, render_png
from tetdose.compare.significance import Z_SIGNIFICANT
from tetdose.compare.slices import SliceFrame
from tetdose.core.image import Image

#: Δ/σ colour scale: ± this.
Z_SCALE = 5.0


def _panel(ax: Any, frame: SliceFrame, values: FloatArray, title: str, **kw: Any) -> Any:  # noqa: ANN401
    im = ax.imshow(values, origin="lower", extent=frame.extent, interpolation="nearest", **kw)
    ax.set_xlim(min(frame.extent[:2]), max(frame.extent[:2]))
    ax.set_ylim(min(frame.extent[2:]), max(frame.extent[2:]))
    ax.set_aspect("equal")
    ax.set_title(title, fontsize=9)
    ax.set_xlabel(frame.axis_labels()[0], fontsize=8)
    ax.tick_params(labelsize=7)
    return im


def significance_figure(ref: Image, difference: FloatArray, z: FloatArray, region: BoolArray,
                        fit_points: BoolArray, *, k: int, labels: tuple[str, str], unit: str
                        ) -> Figure:
    """Axial slice k of a − b and of Δ/σ inside ``region`` (points with |Δ/σ| >
    :data:`~tetdose.compare.significance.Z_SIGNIFICANT` ringed), and the histogram of Δ/σ over
    ``fit_points`` (all slices) with the unit Gaussian two unbiased runs would give."""
    frame = SliceFrame(ref, k)
    d = np.where(region[k], difference[k], np.nan)
    zs = np.where(region[k], z[k], np.nan)
    plt = pyplot()
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.8), layout="constrained")
    lim = float(np.nanpercentile(np.abs(d), 99.5)) if np.isfinite(d).any() else 1.0
    im = _panel(axes[0], frame, d, f"{labels[0]} − {labels[1]} [{unit}]", cmap="RdBu_r",
                vmin=-lim, vmax=lim)
    fig.colorbar(im, ax=axes[0], shrink=0.7)
    im = _panel(axes[1], frame, zs, f"Δ/σ (circled: |Δ/σ| > {Z_SIGNIFICANT:g})",
                cmap="RdBu_r", vmin=-Z_SCALE, vmax=Z_SCALE)
    fig.colorbar(im, ax=axes[1], shrink=0.7)
    jj, ii = np.nonzero(np.abs(np.nan_to_num(zs)) > Z_SIGNIFICANT)
    g = ref.grid
    xs = frame.to_display(np.stack([ii * g.spacing_mm[0], jj * g.spacing_mm[1]], axis=1))
    axes[1].scatter(xs[:, 0], xs[:, 1], s=14, facecolors="none", edgecolors="black",
                    linewidths=0.6)
    zf = z[fit_points & np.isfinite(z)]
    edges = np.linspace(-6.0, 6.0, 61)
    counts, _ = np.histogram(np.clip(zf, -6.0, 6.0), bins=edges)
    centres = 0.5 * (edges[1:] + edges[:-1])
    gauss = zf.size * (edges[1] - edges[0]) * np.exp(-0.5 * centres**2) / np.sqrt(2 * np.pi)
    axes[2].step(centres, counts, where="mid", label=f"measured ({zf.size} points)")
    axes[2].plot(centres, gauss, "k--", label="unit Gaussian (noise only)")
    if counts.any():
        axes[2].set_yscale("log")
        axes[2].set_ylim(bottom=0.5)
    axes[2].set_xlabel("Δ/σ", fontsize=8)
    axes[2].legend(fontsize=7)
    axes[2].set_title("Δ/σ over the compared points above the threshold", fontsize=9)
    fig.suptitle(f"Slice k = {k} (z = {frame.z_mm:.1f} mm): difference and normalised "
                 "difference, σ = sqrt(σ_a² + σ_b²)", fontsize=10)
    return Figure(f"significance_k{k}", f"Difference, normalised difference Δ/σ (|Δ/σ| > "
                  f"{Z_SIGNIFICANT:g} circled) and its histogram against the unit Gaussian",
                  render_png(fig), {"k": k, "difference": d, "z": zs, "histogram_edges": edges,
                                    "histogram_counts": counts, "unit_gaussian": gauss})


def sigma_maps_figure(ref: Image, rel_a: FloatArray | None, rel_b: FloatArray | None,
                      region: BoolArray, *, k: int, labels: tuple[str, str]) -> Figure:
    """Relative σ [%] of both doses on axial slice k inside ``region`` (a dose without σ: a
    blank panel saying so)."""
    frame = SliceFrame(ref, k)
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.8), layout="constrained")
    data: dict[str, Any] = {"k": k}
    shown = [100.0 * np.where(region[k], r[k], np.nan) for r in (rel_a, rel_b) if r is not None]
    top = max([float(np.nanpercentile(s, 95)) for s in shown if np.isfinite(s).any()] or [1.0])
    for ax, rel, name in zip(axes, (rel_a, rel_b), labels, strict=True):
        if rel is None:
            ax.text(0.5, 0.5, f"{name}: no σ given\n(compared as exact)", ha="center",
                    va="center", transform=ax.transAxes)
            ax.set_axis_off()
            continue
        pct = 100.0 * np.where(region[k], rel[k], np.nan)
        im = _panel(ax, frame, pct, f"{name}: σ/D [%]", cmap="magma", vmin=0.0, vmax=top)
        fig.colorbar(im, ax=ax, shrink=0.7)
        data[name] = pct
    return Figure(f"sigma_k{k}", f"Relative standard deviation σ/D [%] of each dose, slice {k}",
                  render_png(fig), data)
