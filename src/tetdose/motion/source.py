"""Motion-source selection and the mass report: what ``tetdose deform`` runs, as a library call.

:func:`phase_series` builds one :class:`~tetdose.motion.phases.PhaseSeries` on a reference mesh
from exactly one motion source — phase meshes (the reference's cells on moved points),
displacement-field images (reference → phase [mm], :mod:`~tetdose.motion.dvf`), target surfaces
(rigid ICP + linear-elastic FEM, :mod:`~tetdose.motion.fem`, extra ``tetdose[fem]``) or the
built-in breathing model (:class:`~tetdose.motion.breathing.BreathingModel`). A real 4D-CT
enters as displacement fields once registered (:mod:`~tetdose.motion.register`).
:func:`deform` adds the mass-conserving density update
(:func:`~tetdose.motion.conserve.update_series`) and :func:`mass_report_csv` its report.

The reference is checked first, the same way for every source: finite, non-negative vertex
densities and a conforming mesh (no duplicated coincident vertices, which would let the mesh
fall apart into disconnected pieces in transport).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from tetdose.core.mesh import TetMesh
from tetdose.errors import OptionError
from tetdose.motion.breathing import BreathingModel
from tetdose.motion.conserve import PhaseReport, reference_density, update_series
from tetdose.motion.fem import POISSON, YOUNG_KPA
from tetdose.motion.phases import PhaseSeries

PathLike = str | os.PathLike[str]

#: Columns of the volume report, one row per phase and region (ΔV/V = V(t)/V(0) − 1).
VOLUME_REPORT_COLUMNS = ("phase_percent", "region", "n_tets", "volume_change_total",
                         "volume_change_min", "volume_change_median", "volume_change_max")
#: Columns of the mass report, one row per phase (units in the names).
MASS_REPORT_COLUMNS = ("phase_percent", "time_weight", "total_mass_g", "mass_change_rel",
                       "min_density_g_cm3", "max_density_g_cm3", "worst_volume_change")


@dataclass(frozen=True)
class FemOptions:
    """Surface-driven FEM settings: load increments, Young's modulus [kPa], Poisson's ratio."""

    n_increments: int = 4
    young_kpa: float = YOUNG_KPA
    poisson: float = POISSON


def phase_series(reference: TetMesh, *, phases: Sequence[PathLike] | None = None,
                 dvfs: Sequence[PathLike] | None = None,
                 surfaces: Sequence[PathLike] | None = None,
                 breathing: BreathingModel | None = None, n_phases: int = 10,
                 phase_percent: Sequence[float] | None = None,
                 fem: FemOptions = FemOptions(),  # noqa: B008 - frozen
                 lung_regions: Sequence[int] | None = None) -> PhaseSeries:
    """The phases of ``reference`` moved by exactly one source (module docstring).

    ``phase_percent``: position of each phase in the cycle [%] (default 100·k/K; the breathing
    model places its ``n_phases`` phases itself; ``lung_regions``: its lung labels, default found
    from the reference density, :func:`~tetdose.motion.breathing.lung_tets`). Raises
    :class:`~tetdose.errors.OptionError` unless exactly one source is given, and the
    reference's checks' errors (module docstring).
    """
    given = [name for name, value in (("phases", phases), ("dvfs", dvfs),
                                      ("surfaces", surfaces), ("breathing", breathing))
             if value is not None]
    if len(given) != 1:
        raise OptionError(f"give exactly one motion source (phase meshes, displacement fields, "
                          f"surfaces or the breathing model), got {given or 'none'}")
    check_reference(reference)
    if breathing is not None:
        return breathing.series(reference, n_phases, lung_regions=lung_regions)
    if phases is not None:
        return PhaseSeries.read(reference, list(phases), phase_percent=phase_percent)
    if dvfs is not None:
        from tetdose.motion.dvf import read_dvf

        points = [read_dvf(f).moved(reference.points_mm) for f in dvfs]
    else:
        from tetdose.motion.fem import surface_driven_points
        from tetdose.motion.surface import read_surface

        points = [surface_driven_points(reference, read_surface(f),
                                        n_increments=fem.n_increments, young_kpa=fem.young_kpa,
                                        poisson=fem.poisson) for f in surfaces or ()]
    return PhaseSeries(reference, np.stack(points), phase_percent)


def check_reference(reference: TetMesh) -> None:
    """Refuse a reference mesh without finite, non-negative point_data ``density`` [g/cm³] or
    with duplicated coincident vertices (a mesh that is not conforming)."""
    reference_density(reference)
    _ = reference.neighbors  # raises MeshError on coincident duplicates


def deform(series: PhaseSeries, *, method: str = "l2") -> tuple[PhaseSeries, list[PhaseReport]]:
    """Per-phase vertex densities keeping every reference tetrahedron's mass, and a report per
    phase (:func:`~tetdose.motion.conserve.update_series`)."""
    return update_series(series, reference_density(series.reference), method=method)


def mass_report_csv(series: PhaseSeries, reports: Sequence[PhaseReport]) -> str:
    """The mass report as CSV text (:data:`MASS_REPORT_COLUMNS`, one row per phase; plain
    round-trip decimal numbers)."""
    rows = [",".join(MASS_REPORT_COLUMNS)]
    for r, w in zip(reports, np.asarray(series.time_weight), strict=True):
        values = (r.phase_percent, w, r.total_mass_g, r.mass_change_rel, r.min_density_g_cm3,
                  r.max_density_g_cm3, r.worst_volume_change)
        rows.append(",".join(repr(float(v)) for v in values))
    return "\n".join(rows) + "\n"


def volume_report_csv(reports: Sequence[PhaseReport]) -> str:
    """Per-region volume change as CSV text (:data:`VOLUME_REPORT_COLUMNS`, one row per phase and
    region)."""
    rows = [",".join(VOLUME_REPORT_COLUMNS)]
    for r in reports:
        for v in r.regions:
            rows.append(",".join([repr(float(r.phase_percent)), str(v.region), str(v.n_tets)]
                                 + [repr(x) for x in (v.total, v.min, v.median, v.max)]))
    return "\n".join(rows) + "\n"
