"""Slice figures of a mapping evaluation, laid out like the paper's Fig. 13 (matplotlib, Agg)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from tetdose._atomic import atomic_write_file
from tetdose.mapping.metrics import Evaluation


def _slices(array: np.ndarray, center: tuple[int, int, int]) -> list[np.ndarray]:
    k, j, i = center
    return [array[k, :, :], array[:, j, :], array[:, :, i]]


def plot_evaluation(ev: Evaluation, path: str | os.PathLike[str], *, title: str = "") -> Path:
    """Axial, coronal and sagittal slices through the ROI centre: original, |error|, reconstruction.

    Densities in g/cm³; rows are views, columns the three images (paper Fig. 13).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    roi = ev.roi.array.astype(bool)
    center = tuple(int(round(c.mean())) for c in np.nonzero(roi))
    sx, sy, sz = ev.original.grid.spacing_mm
    aspects = [sy / sx, sz / sx, sz / sy]
    views = ["axial", "coronal", "sagittal"]
    vmax = float(np.percentile(ev.original.array[roi], 99.5)) * 1.05
    emax = max(float(ev.abs_error.array.max()), 1e-6)
    fig, axes = plt.subplots(3, 3, figsize=(10, 9.5), constrained_layout=True)
    columns = [(ev.original.array, "original", "gray", 0.0, vmax),
               (ev.abs_error.array, "|error|", "magma", 0.0, emax),
               (ev.reconstruction.array, "reconstruction", "gray", 0.0, vmax)]
    for c, (arr, name, cmap, lo, hi) in enumerate(columns):
        for r, sl in enumerate(_slices(arr, center)):
            ax = axes[r, c]
            im = ax.imshow(sl, cmap=cmap, vmin=lo, vmax=hi, origin="lower", aspect=aspects[r],
                           interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title(name)
            if c == 0:
                ax.set_ylabel(views[r])
        fig.colorbar(im, ax=axes[:, c], shrink=0.6, label="g/cm³")
    m = ev.metrics
    fig.suptitle(f"{title} RMDE {m.rmde_pct:.2f} %, ESD {m.esd_pct:.2f} %, mass error "
                 f"{m.mass_error_in_mesh_pct:.2g} % (in mesh)".strip())
    path = Path(path)
    with atomic_write_file(path) as tmp:
        fig.savefig(tmp, dpi=90, format="png")
    plt.close(fig)
    return path
