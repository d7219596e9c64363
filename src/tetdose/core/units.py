"""Is a mesh in mm? Its size and placement against an image of the same patient tell.

tetdose works in mm. A mesh written in metres or centimetres by another tool is read as mm and
would be mapped and dosed as a thing 1000 or 10 times too small (a 15 cm lung in metres spans
0.15 mm: less than one voxel). :func:`check_mesh_on_grid` refuses a mesh whose extent is
implausible for an image grid of the patient (the CT, a dose grid, a displacement field):

1. its largest extent is at most the largest voxel spacing (smaller than one voxel);
2. its largest extent is ≥ :data:`TOO_LARGE` times the grid's (≥ 10× off in size);
3. (unit not stated) it lies inside the grid, covers less than :data:`SMALL_FRACTION` of the
   grid's volume, and scaled by 10 (cm) or 1000 (m) about the patient origin it would still lie
   inside the grid — a small structure in mm is possible, so this case names ``--mesh-unit mm``
   as the way to say so;
4. (unit not stated) it lies wholly outside the grid while scaled by 10 or 1000 it lies inside.
5. (unit stated) read in that unit it lies mostly (> :data:`OUTSIDE_STATED`) outside the grid,
   while read in another unit it lies inside and covers at least :data:`SMALL_FRACTION` of the
   grid (a mm liver given ``--mesh-unit cm`` is 10× too large and mostly off the CT).

The likely unit is the scale (m: 1000, cm: 10, in that order) whose scaled mesh lies inside the
grid. The message names it and the option ``--mesh-unit mm|cm|m`` (Python:
:func:`tetdose.core.io.mesh_unit_policy`), which scales the points by :data:`MESH_UNITS` when the
mesh is read.
"""

from __future__ import annotations

import numpy as np

from tetdose._typing import FloatArray
from tetdose.core.image import ImageGrid
from tetdose.errors import GeometryMismatchError

#: mm per unit of the mesh's coordinates.
MESH_UNITS = {"mm": 1.0, "cm": 10.0, "m": 1000.0}
#: A mesh this many times larger than the grid (largest extents) is refused.
TOO_LARGE = 10.0
#: Below this fraction of the grid's volume a mesh inside it is suspect (rule 3).
SMALL_FRACTION = 0.01
#: Fraction of (sampled) mesh points inside the grid for the mesh to "lie inside" it.
INSIDE_FRACTION = 0.9
#: Fraction of a mesh in a stated unit outside the grid above which another unit is tried.
OUTSIDE_STATED = 0.5
#: Points sampled for the placement tests.
MAX_SAMPLES = 20_000


def _inside_fraction(points_mm: FloatArray, grid: ImageGrid) -> float:
    lo, hi = grid.bounds_grid_frame()
    q = grid.to_grid_frame(points_mm)
    return float(np.mean(np.all((q >= lo) & (q <= hi), axis=1)))


def likely_unit(points_mm: FloatArray, grid: ImageGrid) -> str | None:
    """"m" or "cm" if the points scaled by 1000 or 10 lie inside ``grid``, else None."""
    for unit in ("m", "cm"):
        if _inside_fraction(points_mm * MESH_UNITS[unit], grid) >= INSIDE_FRACTION:
            return unit
    return None


def check_mesh_on_grid(points_mm: FloatArray, volume_mm3: float, grid: ImageGrid, *,
                       mesh_what: str = "the mesh", grid_what: str = "the image",
                       unit: str | None = None) -> None:
    """Refuse a mesh (points [mm], total volume [mm³]) implausible for ``grid`` (module doc).

    ``unit``: the unit the user stated (None: not stated, rules 3 and 4 apply too).
    """
    pts = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
    if len(pts) == 0:
        return
    if len(pts) > MAX_SAMPLES:
        pts = pts[np.linspace(0, len(pts) - 1, MAX_SAMPLES).astype(np.intp)]
    q = grid.to_grid_frame(pts)
    extent = float((q.max(axis=0) - q.min(axis=0)).max())
    lo, hi = grid.bounds_grid_frame()
    grid_extent = float((hi - lo).max())
    voxel = float(grid.spacing_mm.max())
    guess = likely_unit(pts, grid)
    stated = f" (read as {unit})" if unit not in (None, "mm") else ""
    fix = (f"pass --mesh-unit {guess}" if guess else "convert the mesh to mm") + \
        ", or convert the mesh to mm" * bool(guess)
    looks = f"its coordinates look like {_name(guess)} (× {MESH_UNITS[guess]:g} it lies inside " \
            f"{grid_what}); " if guess else ""
    if extent <= voxel:
        raise GeometryMismatchError(
            f"{mesh_what}{stated} spans {extent:.3g} mm, not more than one voxel of {grid_what} "
            f"({voxel:.3g} mm): tetdose works in mm; {looks}{fix}")
    if extent >= TOO_LARGE * grid_extent:
        raise GeometryMismatchError(
            f"{mesh_what}{stated} spans {extent:.4g} mm, {extent / grid_extent:.0f}× the "
            f"{grid_extent:.4g} mm of {grid_what}: one of them is not in mm; convert the mesh "
            "(or the image) to mm")
    if unit is not None:
        _check_stated(pts, volume_mm3, grid, unit, mesh_what, grid_what)
        return
    if guess is None:
        return
    inside = _inside_fraction(pts, grid)
    grid_volume = float(np.prod(hi - lo))
    if inside >= INSIDE_FRACTION and volume_mm3 < SMALL_FRACTION * grid_volume:
        raise GeometryMismatchError(
            f"{mesh_what} spans {extent:.3g} mm and covers {100 * volume_mm3 / grid_volume:.2g} "
            f"% of {grid_what} while lying inside it: {looks}pass --mesh-unit {guess}, or "
            "--mesh-unit mm if it really is that small")
    if inside == 0.0:
        raise GeometryMismatchError(
            f"{mesh_what} lies wholly outside {grid_what}: {looks}{fix}")


def _check_stated(pts: FloatArray, volume_mm3: float, grid: ImageGrid, unit: str,
                  mesh_what: str, grid_what: str) -> None:
    """Rule 5 of the module doc: question a stated unit that puts the mesh off the image."""
    outside = 1.0 - _inside_fraction(pts, grid)
    if outside <= OUTSIDE_STATED:
        return
    lo, hi = grid.bounds_grid_frame()
    grid_volume = float(np.prod(hi - lo))
    for other in MESH_UNITS:
        ratio = MESH_UNITS[other] / MESH_UNITS[unit]
        if (other != unit and _inside_fraction(pts * ratio, grid) >= INSIDE_FRACTION
                and volume_mm3 * ratio**3 >= SMALL_FRACTION * grid_volume):
            raise GeometryMismatchError(
                f"{mesh_what} read in {unit} (--mesh-unit {unit}) lies {100 * outside:.0f} % "
                f"outside {grid_what}, while read in {other} it lies inside it: its "
                f"coordinates look like {_name(other)}; pass --mesh-unit {other}")


def _name(unit: str | None) -> str:
    return {"m": "metres", "cm": "centimetres"}.get(unit or "", "mm")
