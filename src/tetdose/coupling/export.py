"""Breathing phases out to codes that track on tetrahedra (``tetdose export-phases``).

Every phase of a :class:`~tetdose.motion.phases.PhaseSeries` is binned into materials
(:mod:`tetdose.coupling.binning`: one mass-keeping density per tet, at most N materials) and
written in one of :data:`FORMATS`:

* ``tetgen``: ``phase_PPP.P.node``/``.ele``/``.material``, an ICRP-145-style phantom per phase
  (:mod:`tetdose.coupling.tetgen`) for Geant4 (``G4Tet``, the ICRP145_HumanPhantoms example),
  TOPAS-MeshGeom and PHITS;
* ``abaqus``: ``phase_PPP.P.inp`` with one element set per material (:mod:`tetdose.coupling
  .abaqus`) for MCNP6's unstructured mesh, and ``phase_PPP.P.material`` with the MCNP ``m``
  cards of its materials.

Tet k of every phase is element k (0-based in ``.ele``, k+1 in ``.inp``), so the codes' per-tet
tallies come back with ``tetdose import-dose``. ``export.json`` records the format, the length
unit (cm), the phases (percent, time weight, files) and each phase's binning (materials, mass,
mass error ε, total mass change Δ).
"""

from __future__ import annotations

import json
import os
import warnings
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from tetdose._atomic import atomic_write_dir
from tetdose._typing import FloatArray, IntArray
from tetdose.core.icrp145 import read_material_file, read_tetgen
from tetdose.core.mesh import COINCIDENT_TOL_MM, PARENT_POINT, TetMesh
from tetdose.coupling.abaqus import read_abaqus, write_abaqus
from tetdose.coupling.binning import DEFAULT_MAX_MASS_ERROR, bin_densities
from tetdose.coupling.tetgen import write_material_file, write_tetgen
from tetdose.errors import MeshError, OptionError, TopologyMismatchError
from tetdose.motion.phases import PhaseSeries
from tetdose.transport.physics.materials import MATERIALS, Material

FORMATS = ("tetgen", "abaqus")
#: The record written beside the phase files.
RECORD = "export.json"


def phase_stem(percent: float) -> str:
    """File stem of a phase, as ``tetdose dose4d`` names its phase outputs."""
    return f"phase_{percent:05.1f}"


def conforming_geometry(mesh: TetMesh) -> tuple[FloatArray, IntArray]:
    """(points [mm], tets) with a region-split mesh's vertex copies joined again.

    A mesh split by region (:meth:`TetMesh.split_by_region`, point_data ``parent_point``) holds
    one copy of an interface vertex per region, for its density jump; the exported files carry
    one density per tet, so the copies are merged back (when they coincide) and the elements
    share their faces, as MCNP's element-to-element tracking needs.
    """
    parent = mesh.point_data.get(PARENT_POINT)
    if parent is None:
        return mesh.points_mm, mesh.tets
    ids, first, inverse = np.unique(np.asarray(parent, dtype=np.int64), return_index=True,
                                    return_inverse=True)
    points = mesh.points_mm[first]
    if np.abs(mesh.points_mm - points[inverse.reshape(-1)]).max() > COINCIDENT_TOL_MM:
        return mesh.points_mm, mesh.tets  # the copies moved apart: keep them apart
    return points, inverse.reshape(-1)[mesh.tets]


def export_phases(series: PhaseSeries, out_dir: str | os.PathLike[str], *, fmt: str = "tetgen",
                  n_bins: int | None = None,
                  region_materials: Mapping[int, str] | None = None,
                  compositions: Mapping[str, Material] | None = None) -> dict[str, object]:
    """Write every phase of ``series`` (module docstring) into ``out_dir`` (atomic); returns the
    record written to ``export.json``, which lists the composition of every material used
    (``compositions``: the plan's ``[materials.NAME]``, besides the built-in names)."""
    if fmt not in FORMATS:
        raise OptionError(f"unknown export format {fmt!r}; choose one of {', '.join(FORMATS)}")
    if series.density_g_cm3 is None:
        raise MeshError("the phases carry no density; run `tetdose deform` (the density update) "
                        "before exporting them")
    phases: list[dict[str, object]] = []
    record: dict[str, object] = {"format": fmt, "length_unit": "cm", "density_unit": "g/cm3",
                                 "n_tets": series.reference.n_tets, "phases": phases}
    binned = [bin_densities(series.mesh(k), n_bins=n_bins, region_materials=region_materials,
                            compositions=compositions) for k in range(series.n_phases)]
    library = {**MATERIALS, **(compositions or {})}
    record["compositions"] = {c: library[c].record() for c in sorted(
        {m.composition for b in binned for m in b.materials})}
    worst = max(b.mass_error for b in binned)
    if n_bins is not None and worst > DEFAULT_MAX_MASS_ERROR:
        warnings.warn(f"{n_bins} density bins leave a mass error of {100 * worst:.3g} % (more "
                      f"than {100 * DEFAULT_MAX_MASS_ERROR:g} %); give more bins or leave "
                      "--density-bins out", stacklevel=2)
    with atomic_write_dir(Path(out_dir)) as tmp:
        for k, b in enumerate(binned):
            stem = phase_stem(float(series.phase_percent[k]))
            points, tets = conforming_geometry(series.mesh(k))
            if fmt == "tetgen":
                paths = write_tetgen(tmp / stem, points, tets, b.material_id, b.materials,
                                     library)
            else:
                paths = [write_abaqus(tmp / f"{stem}.inp", points, tets, b.material_id,
                                      b.materials,
                                      title=f"tetdose {stem} ({series.phase_percent[k]:g} %)"),
                         write_material_file(tmp / f"{stem}.material", b.materials, library)]
            phases.append(
                {"phase_percent": float(series.phase_percent[k]),
                 "time_weight": float(series.time_weight[k]),
                 "files": [p.name for p in paths], **b.summary()})
        (tmp / RECORD).write_text(json.dumps(record, indent=2) + "\n")
    return record


def exported_densities(folder: str | os.PathLike[str], n_tets: int,
                       phase_percent: FloatArray | None = None) -> list[FloatArray]:
    """Per phase, the per-tet density [g/cm³] the exported files give (read back from them);
    given ``phase_percent`` [%], in the order of those phases, matched by the export's record
    (an export of other phases is refused)."""
    folder = Path(folder)
    try:
        record = json.loads((folder / RECORD).read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise MeshError(f"{folder / RECORD} cannot be read ({exc}); give the folder written by "
                        "`tetdose export-phases`") from None
    phases = record["phases"]
    if phase_percent is not None:
        got = [float(p.get("phase_percent", np.nan)) for p in phases]
        want = [float(p) for p in phase_percent]
        pick = [int(np.argmin(np.abs(np.asarray(got) - w))) if got else -1 for w in want]
        if len(got) != len(want) or any(abs(got[i] - w) > 0.05 for i, w in zip(pick, want,
                                                                                strict=True)):
            raise MeshError(f"{folder} exports phases at {got} %, the phases are at {want} %; "
                            "give the export of these phases (`tetdose export-phases`)")
        phases = [phases[i] for i in pick]
    out = []
    for phase in phases:
        first = folder / phase["files"][0]
        if record["format"] == "tetgen":
            _, tets, mat = read_tetgen(first)
            rho_of = {k: m.density_g_cm3 for k, m in read_material_file(first).items()}
        else:
            _, tets, mat, rho_of = read_abaqus(first)
        if len(tets) != n_tets or mat is None:
            raise TopologyMismatchError(f"{first} holds {len(tets)} tetrahedra, the phases "
                                        f"{n_tets}; give the export of these phases")
        lookup = np.full(int(max(max(rho_of, default=0), mat.max())) + 1, np.nan)
        lookup[list(rho_of)] = list(rho_of.values())
        rho = lookup[mat]
        if not np.all(rho > 0):
            raise MeshError(f"{first}: some tetrahedra have a material without a density > 0; "
                            "export the phases again")
        out.append(rho)
    return out
