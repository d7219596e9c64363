"""What a dose is: dose to medium (D_m, what Monte Carlo transports and scores) or dose to water
(D_w = D_m · s_w,m, :mod:`tetdose.transport.run.water`), and where outputs say so.

Every output records it (AAPM TG-105: a Monte Carlo system must state which it reports):

- JSON run records and ``summary.json``: ``"dose_to": "medium" | "water"`` (with
  ``"dose_to_water"``: the method — per cell from the tracked electron fluence,
  :mod:`tetdose.transport.run.water`, or per medium — the ratio s_w,m of each medium, and the
  cells that fell back to the per-medium ratio, for D_w); a transport run's VTU also has the
  per-cell ratios (cell array ``s_w_m``);
- VTU meshes: the cell array ``dose_to_water`` (int8, 1 where the ``dose`` arrays are D_w, 0 for
  D_m), read back by :func:`recorded_dose_to`;
- RT Dose: DoseComment and SeriesDescription (:func:`tetdose.dicom.rt_dose.write_rt_dose`).

Commands that read a dose (``export-dose``, ``compare``) take the one recorded beside it (a
file without a record is dose to medium) and refuse a ``--dose-to`` that differs: converting
needs each cell's medium, which only a transport run knows (``tetdose dose --dose-to water``).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from tetdose.core.mesh import TetMesh
from tetdose.errors import OptionError

#: The two quantities, default first.
DOSE_TO = ("medium", "water")
#: Name of the VTU cell array that says which dose the mesh's dose arrays are.
ARRAY = "dose_to_water"


def mark(mesh: TetMesh, dose_to: str) -> TetMesh:
    """``mesh`` with the cell array :data:`ARRAY` (1 for dose to water, 0 for medium)."""
    check(dose_to)
    return mesh.with_data(cell_data={ARRAY: np.full(mesh.n_tets, dose_to == "water", np.int8)})


def check(dose_to: str) -> str:
    if dose_to not in DOSE_TO:
        raise OptionError(f"dose to {dose_to!r} is unknown; use one of {DOSE_TO}")
    return dose_to


def recorded_dose_to(dose_path: str | Path, mesh: TetMesh | None = None) -> str:
    """What the dose at ``dose_path`` is: the ``dose_to`` of the record beside it
    (``<stem>.json`` of ``tetdose dose``, ``summary.json`` of ``dose4d``/``import-dose``), else
    the VTU's :data:`ARRAY` (``mesh``), else "medium"."""
    path = Path(dose_path)
    for record in (path.with_name(path.name.split(".")[0] + ".json"),
                   path.with_name("summary.json")):
        try:
            value = json.loads(record.read_text(encoding="utf-8")).get("dose_to")
        except (OSError, ValueError, AttributeError):
            continue
        if value in DOSE_TO:
            return str(value)
    if mesh is not None and ARRAY in mesh.cell_data:
        return DOSE_TO[int(np.asarray(mesh.cell_data[ARRAY]).max(initial=0) > 0)]
    return DOSE_TO[0]


def require_same(requested: str | None, recorded: str, what: str) -> str:
    """``recorded``, after checking that ``requested`` (a ``--dose-to``, None: any) is it."""
    if requested is not None and check(requested) != recorded:
        raise OptionError(f"{what} is dose to {recorded}, not to {requested}; converting needs "
                          f"each cell's medium: run `tetdose dose --dose-to {requested}` "
                          "(or drop --dose-to)")
    return recorded
