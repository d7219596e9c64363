"""Comparison report: dose slices, difference and gamma maps, DVHs, profiles → HTML + JSON.

:func:`write_report` writes into one folder, atomically: ``report.html`` (self-contained, the PNG
figures embedded as base64), one ``<figure>.png`` per figure, ``figures.json`` holding the data
drawn in every figure (arrays as nested lists, NaN as null) and ``summary.json`` (the numbers of
the summary table). Figures use matplotlib's Agg backend (no display needed).
"""

from __future__ import annotations

import base64
import html
import io
import json
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from tetdose._atomic import atomic_write_dir
from tetdose._constants import MM3_PER_CM3
from tetdose._typing import FloatArray
from tetdose.compare.dvh import DVH
from tetdose.compare.dvh_bands import BandedDVH
from tetdose.compare.gamma import GammaResult
from tetdose.compare.profiles import Profile
from tetdose.compare.slices import ISODOSE_FRACTIONS, SliceFrame, draw_dose_wash
from tetdose.core.body import near_max_gy
from tetdose.core.image import Image
from tetdose.core.mesh import TetMesh
from tetdose.plan.prescription import PER_PHOTON_UNIT


@dataclass
class Figure:
    """A rendered figure: its name, caption, PNG bytes and the data it shows."""

    name: str
    caption: str
    png: bytes
    data: dict[str, Any] = field(default_factory=dict)


def render_png(fig: Any) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100, bbox_inches="tight")
    import matplotlib.pyplot as plt

    plt.close(fig)
    return buf.getvalue()


def pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def wash_top(prescription_gy: float | None, *slices: FloatArray) -> float:
    """Top of the dose colour scale [Gy]: 1.25 × the prescription, else the 99.5th percentile
    of the slices' scored doses — a Monte Carlo dose's single hottest voxel is noise, not the
    scale a reader needs."""
    if prescription_gy:
        return 1.25 * float(prescription_gy)
    scored = np.concatenate([np.asarray(x, float).ravel() for x in slices])
    scored = scored[scored > 0]
    return float(np.percentile(scored, 99.5)) if scored.size else 1e-30


def dose_slices_figure(a: Image, b: Image, *, labels: tuple[str, str] = ("mesh", "voxel"),
                       k: int | None = None, unit: str = PER_PHOTON_UNIT,
                       ct_hu: Image | None = None, mesh: TetMesh | None = None,
                       structures: Mapping[str, int] | None = None,
                       prescription_gy: float | None = None,
                       region: np.ndarray | None = None) -> Figure:
    """Axial slice k (default: through the maximum of ``a``) of both doses and a − b.

    Each dose is a colour wash over the CT (``ct_hu`` on the same grid, grey, HU −1000…400) with
    isodose lines at 95/50/20 % of ``prescription_gy`` (else of the near-maximum D0.1cm³ of ``a``
    on the slice, in ``region`` when given) and
    the surfaces of ``mesh`` cut by the slice (one contour per ``structures`` name → region label,
    else the whole mesh), axes in mm (:mod:`tetdose.compare.slices`). ``unit``: "Gy" for
    prescribed doses, else doses are per source photon (the default); ``region`` (boolean, the
    grid's shape): the difference is drawn there only (the compared tissue, not air)."""
    if k is None:
        k = int(np.unravel_index(int(np.argmax(a.array)), a.array.shape)[0])
    sa, sb = np.asarray(a.array[k], float), np.asarray(b.array[k], float)
    diff = sa - sb
    if region is not None:
        diff = np.where(np.asarray(region, bool)[k], diff, np.nan)
    frame = SliceFrame(a, k)
    ct = None
    if ct_hu is not None and ct_hu.array.shape == a.array.shape:
        ct = np.asarray(ct_hu.array[k], float)
    tissue = np.ones(sa.shape, bool) if region is None else np.asarray(region, bool)[k]
    near = near_max_gy(np.where(tissue, sa, 0.0), a.grid.voxel_volume_mm3 / MM3_PER_CM3)
    reference = prescription_gy if prescription_gy else max(near, 1e-30)
    isodose = [f * reference for f in ISODOSE_FRACTIONS]
    contours = {}
    if mesh is not None:
        named = structures or {"mesh": None}
        contours = {name: frame.contours(mesh, label) for name, label in named.items()}
    plt = pyplot()
    fig, axes = plt.subplots(1, 3, figsize=(15, 5), layout="constrained")
    top = wash_top(prescription_gy, sa, sb)
    for ax, img, title in ((axes[0], sa, labels[0]), (axes[1], sb, labels[1])):
        im = draw_dose_wash(ax, frame, img, top_gy=top, ct_slice=ct, isodose_gy=isodose,
                            contours=contours)
        ax.set_title(title, fontsize=9)
        fig.colorbar(im, ax=ax, shrink=0.7, label=unit)
    lim = max(float(np.nanmax(np.abs(diff))) if np.isfinite(diff).any() else 0.0, 1e-30)
    im = axes[2].imshow(diff, origin="lower", extent=frame.extent, cmap="RdBu_r", vmin=-lim,
                        vmax=lim, interpolation="nearest")
    axes[2].set_xlim(min(frame.extent[:2]), max(frame.extent[:2]))
    axes[2].set_ylim(min(frame.extent[2:]), max(frame.extent[2:]))
    axes[2].set_aspect("equal")
    axes[2].set_title(f"{labels[0]} − {labels[1]}", fontsize=9)
    axes[2].set_xlabel(frame.axis_labels()[0], fontsize=8)
    axes[2].tick_params(labelsize=7)
    fig.colorbar(im, ax=axes[2], shrink=0.7, label=unit)
    basis = (f"{prescription_gy:g} Gy prescribed" if prescription_gy
             else f"the slice's near-maximum (D0.1cm³) {reference:.3g} {unit}")
    fig.suptitle(f"Axial slice k = {k} (z = {frame.z_mm:.1f} mm); isodoses 95/50/20 % of {basis}",
                 fontsize=10)
    data = {"k": k, "z_mm": frame.z_mm, "extent_mm": frame.extent, labels[0]: sa, labels[1]: sb,
            "difference_gy": diff, "isodose_gy": isodose,
            "contour_segments": {n: int(len(c)) for n, c in contours.items()}}
    return Figure(f"dose_slice_k{k}", f"Axial slice {k} (z = {frame.z_mm:.1f} mm): doses over the "
                  f"CT with isodoses and organ contours, and their difference [{unit}]",
                  render_png(fig), {**data, "unit": unit})


def gamma_figure(result: GammaResult, *, k: int, expected: float | None = None) -> Figure:
    """Gamma map of axial slice k (NaN = not evaluated; values above 2 clipped for display);
    ``expected``: the pass rate [%] noise alone would give (in the title)."""
    g = result.gamma[k]
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6, 4.5))
    im = ax.imshow(np.clip(g, 0, 2), origin="lower", cmap="RdYlGn_r", vmin=0, vmax=2)
    crit = result.summary()["criterion"]
    noise = f" (two unbiased runs: {expected:.1f} %)" if expected is not None else ""
    ax.set_title(f"γ {crit}: {result.pass_rate_percent:.2f} % pass{noise}", fontsize=9)
    fig.colorbar(im, ax=ax, shrink=0.8)
    name = "gamma_" + str(crit).replace("%", "pct").replace("/", "_").replace(" ", "_")
    return Figure(f"{name}_k{k}", f"Gamma {crit}, slice {k}", render_png(fig),
                  {"k": k, "gamma": g, **result.summary()})


def dvh_figure(curves: Mapping[str, Sequence[DVH | BandedDVH]], *, unit: str = PER_PHOTON_UNIT,
               build_up_mm: float | None = None,
               build_up_fraction: Mapping[str, float] | None = None,
               below_kerma_fraction: Mapping[str, float] | None = None) -> Figure:
    """Cumulative DVHs, one colour per structure, one line style per dose source; a
    :class:`~tetdose.compare.dvh_bands.BandedDVH` is drawn with its ±1σ band (shaded).

    ``unit``: "Gy" for prescribed doses; ``build_up_mm``: the beams' build-up depth d_max, noted
    in the caption (cells shallower than it report kerma, which exceeds the dose there), and
    ``build_up_fraction`` per structure (:mod:`tetdose.dose.buildup`) in the legend — for kerma
    runs; a dose run gives instead ``below_kerma_fraction``, the measured mass fraction where the
    dose lies below 95 % of the kerma (:mod:`tetdose.compare.dose_kerma`)."""
    build_up_fraction = build_up_fraction or {}
    below_kerma_fraction = below_kerma_fraction or {}
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(10, 4.5), layout="constrained")
    top = max(float(_plain(h).dose_gy[0]) for hs in curves.values() for h in hs)
    levels = np.linspace(0.0, 1.05 * top, 200)
    data: dict[str, Any] = {"dose_gy": levels, "unit": unit,
                            "build_up_fraction": dict(build_up_fraction),
                            "below_kerma_fraction": dict(below_kerma_fraction)}
    for colour, (structure, hs) in enumerate(curves.items()):
        for style, item in zip(("-", "--", ":"), hs, strict=False):
            h = _plain(item)
            v = h.curve(levels)
            banded = isinstance(item, BandedDVH) and bool(item.replicas)
            if banded:
                lo, hi = item.band(levels)
                ax.fill_between(levels, lo, hi, color=f"C{colour % 10}", alpha=0.2, lw=0)
                data[f"{structure}/{h.name}/band_percent"] = {"p16": lo, "p84": hi}
            frac = build_up_fraction.get(structure, 0.0)
            note = f", {100 * frac:.0f} % in build-up" if frac > 0 else ""
            below = below_kerma_fraction.get(structure, 0.0)
            if below > 0:
                note += f", {100 * below:.0f} % below 0.95 kerma (measured)"
            m = h.metrics()
            ax.plot(levels, v, style, color=f"C{colour % 10}",
                    label=f"{structure} ({h.name}): D95 {m['D95']:.3g}, D2 {m['D2']:.3g}, "
                          f"Dmean {m['Dmean']:.3g}{note}")
            data[f"{structure}/{h.name}"] = {"volume_percent": v, **h.metrics()}
    ax.set_xlabel(f"dose [{unit}]")
    ax.set_ylabel("volume [%]")
    ax.set_title(f"Cumulative DVHs (legend: D95, D2, Dmean in {unit}; shaded: ±1σ band "
                 "from the doses' σ)", fontsize=9)
    ax.legend(fontsize=6, loc="center left", bbox_to_anchor=(1.01, 0.5))
    caption = "Cumulative dose–volume histograms"
    if build_up_mm is not None:
        caption += (f"; structures within {build_up_mm:g} mm of the skin lie in the build-up "
                    "region, where kerma (what is scored) exceeds the absorbed dose")
    return Figure("dvh", caption, render_png(fig), data)


def _plain(h: DVH | BandedDVH) -> DVH:
    return h.dvh if isinstance(h, BandedDVH) else h


def profiles_figure(profiles: Sequence[Profile], *, name: str = "profile",
                    unit: str = PER_PHOTON_UNIT) -> Figure:
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 4))
    data: dict[str, Any] = {}
    for p in profiles:
        ax.plot(p.distance_mm, p.dose_gy, label=p.label)
        data[p.label] = {"distance_mm": p.distance_mm, "dose_gy": p.dose_gy,
                         "start_mm": p.points_mm[0], "end_mm": p.points_mm[-1]}
    ax.set_xlabel("distance along the line [mm]")
    ax.set_ylabel(f"dose [{unit}]")
    ax.legend()
    return Figure(name, f"Dose profile {name} [{unit}]", render_png(fig), {**data, "unit": unit})


def _jsonable(x: Any) -> Any:
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, np.generic):
        x = x.item()
    if isinstance(x, float) and not np.isfinite(x):
        return None
    return x


def write_report(out_dir: str | os.PathLike[str], figures: Sequence[Figure],
                 summary: Mapping[str, Any], *, title: str = "tetdose dose comparison") -> Path:
    """Write the report folder (module docstring) atomically; return its path."""
    out = Path(out_dir)
    rows = "".join(f"<tr><th>{html.escape(str(k))}</th><td>{html.escape(_fmt(v))}</td></tr>"
                   for k, v in _flatten(summary).items())
    blocks = "".join(
        f"<figure><img alt='{html.escape(f.name)}' src='data:image/png;base64,"
        f"{base64.b64encode(f.png).decode()}'/><figcaption>{html.escape(f.caption)}"
        "</figcaption></figure>" for f in figures)
    page = (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(title)}"
            "</title><style>body{font-family:sans-serif;margin:2em}td,th{padding:2px 8px;"
            "text-align:left}img{max-width:100%}</style></head><body>"
            f"<h1>{html.escape(title)}</h1><table>{rows}</table>{blocks}</body></html>")
    with atomic_write_dir(out) as tmp:
        (tmp / "report.html").write_text(page, encoding="utf-8")
        for f in figures:
            (tmp / f"{f.name}.png").write_bytes(f.png)
        (tmp / "figures.json").write_text(
            json.dumps({f.name: _jsonable(f.data) for f in figures}), encoding="utf-8")
        (tmp / "summary.json").write_text(json.dumps(_jsonable(dict(summary)), indent=2),
                                          encoding="utf-8")
    return out


def _flatten(d: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, Mapping):
            out |= _flatten(v, f"{prefix}{k} / ")
        else:
            out[f"{prefix}{k}"] = v
    return out


def _fmt(v: Any) -> str:
    return f"{v:.5g}" if isinstance(v, float) else str(v)
