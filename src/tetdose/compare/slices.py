"""Dose slices as a physicist reads them: colour wash over the CT, isodose lines, organ contours.

An axial slice is the plane of constant third grid index k. Everything is drawn in the grid's own
frame, in mm from the patient origin: a pixel (i, j) sits at ``origin + (i·Δx, j·Δy)`` along the
grid's first two axes, which are the patient x and y for the usual axial DICOM orientation
(direction = identity, or diagonal ±1: axes are then flipped so that +x and +y grow right and up).
For any other orthonormal direction the axis labels say "grid frame".

Organ contours are the **mesh's own surfaces cut by the slice plane**: for each region, the faces
of its tets whose neighbour lies in another region (or outside) are intersected with the plane
q₃ = k·Δz (q = Dᵀ(p − origin), the grid frame), which gives one segment per cut triangle. These
are the surfaces the transport sees, not a re-contoured voxel mask.

Isodose lines at 95/50/20 % of the prescription (or of the slice's reference maximum when the dose
is not prescribed) are :func:`matplotlib.axes.Axes.contour` lines of the dose slice.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from tetdose._typing import FloatArray
from tetdose.core.image import Image
from tetdose.core.mesh import FACE_VERTICES, TetMesh

#: Isodose levels drawn, as fractions of the prescription (or of the reference maximum).
ISODOSE_FRACTIONS = (0.95, 0.5, 0.2)
#: CT display window [HU].
CT_WINDOW_HU = (-1000.0, 400.0)
#: Doses below this fraction of the colour scale's top are not washed (the CT shows through).
WASH_FLOOR = 0.05
#: Contour colours (bright, apart from the wash's blue–red) and isodose line styles.
CONTOUR_COLOURS = ("magenta", "lime", "cyan", "yellow", "orange", "white")
ISODOSE_STYLES = ("solid", "dashed", "dotted")


def region_faces(mesh: TetMesh, region: int | None = None) -> FloatArray:
    """(F, 3, 3) corner points [mm] of the surface of ``region`` (default: the whole mesh): the
    faces of its tets whose neighbour is outside the mesh or in another region."""
    nb = mesh.neighbors
    if region is None or mesh.region is None:
        inside = np.ones(mesh.n_tets, dtype=bool)
    else:
        inside = mesh.region == region
    other = np.where(nb >= 0, ~inside[np.maximum(nb, 0)], True)
    k, f = np.nonzero(inside[:, None] & other)
    return mesh.points_mm[mesh.tets[k[:, None], FACE_VERTICES[f]]]


def plane_section(triangles_grid: FloatArray, z: float) -> FloatArray:
    """(S, 2, 2) segments (first two coordinates) where triangles (F, 3, 3), given in a frame
    whose third axis is normal to the plane, cross the plane ``third coordinate = z``.

    Vertices exactly on the plane are nudged by 1e-9 of the triangles' extent so that every cut
    triangle gives exactly two crossing edges."""
    if len(triangles_grid) == 0:
        return np.zeros((0, 2, 2))
    s = triangles_grid[..., 2] - z
    scale = max(float(np.ptp(triangles_grid[..., 2])), 1.0)
    s = np.where(s == 0.0, 1e-9 * scale, s)
    cut = (s.min(axis=1) < 0.0) & (s.max(axis=1) > 0.0)
    tri, s = triangles_grid[cut], s[cut]
    points = []
    for a, b in ((0, 1), (1, 2), (2, 0)):
        crosses = s[:, a] * s[:, b] < 0.0
        t = np.where(crosses, s[:, a] / np.where(crosses, s[:, a] - s[:, b], 1.0), 0.0)
        p = tri[:, a, :2] + t[:, None] * (tri[:, b, :2] - tri[:, a, :2])
        points.append((crosses, p))
    first = np.where(points[0][0][:, None], points[0][1], points[1][1])
    second = np.where(points[2][0][:, None], points[2][1], points[1][1])
    return np.stack([first, second], axis=1)


class SliceFrame:
    """The 2-D frame of axial slice ``k`` of a grid: extents, flips and the map of points into it."""

    def __init__(self, image: Image, k: int) -> None:
        g = image.grid
        self.grid, self.k = g, int(k)
        d = np.asarray(g.direction, dtype=np.float64)
        self.axis_aligned = bool(np.allclose(np.abs(d), np.eye(3), atol=1e-6))
        self.sign = np.sign(np.diag(d)) if self.axis_aligned else np.ones(3)
        self.sign[self.sign == 0] = 1.0
        n_j, n_i = image.array.shape[1], image.array.shape[2]
        half = 0.5 * np.asarray(g.spacing_mm, dtype=np.float64)
        lo = -half[:2]
        hi = np.array([(n_i - 1) * g.spacing_mm[0], (n_j - 1) * g.spacing_mm[1]]) + half[:2]
        o = np.asarray(g.origin_mm, dtype=np.float64)
        # display coordinate u = origin + sign·q along each axis (patient mm when axis-aligned)
        self.extent = [o[0] + self.sign[0] * lo[0], o[0] + self.sign[0] * hi[0],
                       o[1] + self.sign[1] * lo[1], o[1] + self.sign[1] * hi[1]]
        self.z_grid_mm = self.k * float(g.spacing_mm[2])
        self.z_mm = float(o[2] + self.sign[2] * self.z_grid_mm)

    def to_grid(self, points_mm: FloatArray) -> FloatArray:
        """Points [mm] (…, 3) in the grid frame q = Dᵀ(p − origin)."""
        g = self.grid
        return (np.asarray(points_mm) - np.asarray(g.origin_mm)) @ np.asarray(g.direction)

    def to_display(self, q_xy: FloatArray) -> FloatArray:
        """Grid-frame (…, 2) coordinates → the display's mm."""
        o = np.asarray(self.grid.origin_mm, dtype=np.float64)
        return o[:2] + self.sign[:2] * q_xy

    def axis_labels(self) -> tuple[str, str]:
        if self.axis_aligned:
            return "x [mm] (patient)", "y [mm] (patient)"
        return "grid x [mm]", "grid y [mm]"

    def contours(self, mesh: TetMesh, region: int | None = None) -> FloatArray:
        """(S, 2, 2) display-frame segments of the surface of ``region`` cut by this slice."""
        tri = self.to_grid(region_faces(mesh, region))
        seg = plane_section(tri, self.z_grid_mm)
        return self.to_display(seg)


def draw_dose_wash(ax: Any, frame: SliceFrame, dose_slice: FloatArray, *,  # noqa: ANN401
                   top_gy: float, ct_slice: FloatArray | None = None,
                   isodose_gy: Sequence[float] = (), contours: Mapping[str, FloatArray] | None = None,
                   cmap: str = "jet") -> Any:  # noqa: ANN401
    """Draw one panel: the CT in grey, the dose as a translucent colour wash above
    :data:`WASH_FLOOR` of ``top_gy``, isodose lines and the organ contour segments. Returns the
    dose image artist (for a colour bar)."""
    from matplotlib.collections import LineCollection

    if ct_slice is not None:
        ax.imshow(ct_slice, origin="lower", extent=frame.extent, cmap="gray",
                  vmin=CT_WINDOW_HU[0], vmax=CT_WINDOW_HU[1], interpolation="nearest")
    wash = np.ma.masked_less(dose_slice, WASH_FLOOR * top_gy)
    im = ax.imshow(wash, origin="lower", extent=frame.extent, cmap=cmap, vmin=0.0, vmax=top_gy,
                   alpha=0.55 if ct_slice is not None else 1.0, interpolation="nearest")
    levels = sorted(x for x in isodose_gy if 0.0 < x < float(np.max(dose_slice)))
    if levels:
        x = np.linspace(frame.extent[0], frame.extent[1], dose_slice.shape[1] + 1)
        y = np.linspace(frame.extent[2], frame.extent[3], dose_slice.shape[0] + 1)
        xc, yc = 0.5 * (x[1:] + x[:-1]), 0.5 * (y[1:] + y[:-1])
        styles = [ISODOSE_STYLES[min(i, 2)] for i in range(len(levels))][::-1]
        cs = ax.contour(xc, yc, dose_slice, levels=levels, colors="black", linewidths=0.9,
                        linestyles=styles)
        ax.clabel(cs, fmt=lambda v: f"{v:.3g}", fontsize=6)
    for colour, (name, seg) in enumerate((contours or {}).items()):
        if len(seg):
            ax.add_collection(LineCollection(
                seg, colors=CONTOUR_COLOURS[colour % len(CONTOUR_COLOURS)], linewidths=1.2,
                label=name))
    if contours:
        ax.legend(loc="upper right", fontsize=6, framealpha=0.6)
    ax.set_xlim(min(frame.extent[:2]), max(frame.extent[:2]))
    ax.set_ylim(min(frame.extent[2:]), max(frame.extent[2:]))
    xlabel, ylabel = frame.axis_labels()
    ax.set_xlabel(xlabel, fontsize=8)
    ax.set_ylabel(ylabel, fontsize=8)
    ax.tick_params(labelsize=7)
    ax.set_aspect("equal")
    return im
