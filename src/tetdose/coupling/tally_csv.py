"""Per-tetrahedron tallies as CSV: what Geant4, PHITS and MCNP6 users write from their scorers.

One header line names the columns (case-insensitive, any order, extra columns ignored), then one
row per tetrahedron; lines starting with '#' are comments:

* the tet: ``tet`` (0-based: tetdose's tet index = the ``.ele`` element id = Geant4's copy
  number of the parameterised tet) **or** ``element`` (1-based: the Abaqus element number
  MCNP6 reports in its elemental edits);
* the quantity: ``energy_mev`` (energy deposited in the tet [MeV]) **or** ``dose_gy`` [Gy];
* optionally its uncertainty: ``sigma_mev`` / ``sigma_gy`` (one standard deviation, same unit)
  or ``rel_err`` (σ as a fraction of the value, as MCNP and PHITS print it).

Every tet of the mesh must appear exactly once (a code that skips unscored tets should write
0 for them), so a tally from another mesh or phase is caught by its row count.
"""

from __future__ import annotations

import csv
import io
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tetdose._atomic import atomic_write_file
from tetdose._typing import FloatArray
from tetdose.errors import DoseError

#: id column → index base.
ID_COLUMNS = {"tet": 0, "element": 1}
#: quantity column → (kind, absolute σ column).
QUANTITIES = {"energy_mev": ("energy", "sigma_mev"), "dose_gy": ("dose", "sigma_gy")}
REL_ERR = "rel_err"


@dataclass(frozen=True, eq=False)
class TetTally:
    """One value per tet [MeV if ``kind`` is "energy", Gy if "dose"] and its σ (same unit)."""

    kind: str
    value: FloatArray
    sigma: FloatArray | None


def read_tally_csv(path: str | os.PathLike[str], n_tets: int) -> TetTally:
    """Read a per-tet tally (module docstring) for a mesh of ``n_tets`` tetrahedra."""
    path = Path(path)
    if not path.is_file():
        raise DoseError(f"{path} does not exist; give a per-tet tally CSV")
    lines = path.read_text(errors="replace").splitlines()
    body = [i for i, ln in enumerate(lines) if ln.strip() and not ln.lstrip().startswith("#")]
    if not body:
        raise DoseError(f"{path} is empty; a tally CSV needs a header and one row per tet")
    header = next(csv.reader([lines[body[0]]]))
    head = [h.strip().lower() for h in header]
    id_col = [c for c in ID_COLUMNS if c in head]
    q_col = [c for c in QUANTITIES if c in head]
    if len(id_col) != 1 or len(q_col) != 1:
        raise DoseError(f"{path}: the header {header} must name one id column (tet: 0-based, or "
                        "element: 1-based) and one quantity (energy_mev or dose_gy)")
    kind, sigma_name = QUANTITIES[q_col[0]]
    s_col = sigma_name if sigma_name in head else REL_ERR if REL_ERR in head else None
    cols = [head.index(c) for c in (id_col[0], q_col[0], s_col) if c is not None]
    try:
        table = np.loadtxt(io.StringIO("\n".join(lines[body[0] + 1:])), delimiter=",",
                           comments="#", usecols=cols, ndmin=2, dtype=np.float64) \
            if len(body) > 1 else np.empty((0, len(cols)))
    except ValueError as exc:
        raise DoseError(f"{path}: a row is short or not numeric ({exc}); fix the file") from None
    if len(table) != n_tets:
        raise DoseError(f"{path} holds {len(table)} tets, the mesh has {n_tets}: the tally "
                        "belongs to another mesh (or skips tets: write 0 for unscored ones)")
    ids = table[:, 0] - ID_COLUMNS[id_col[0]]
    if (np.any(ids != np.rint(ids)) or ids.min() < 0 or ids.max() >= n_tets
            or len(np.unique(ids)) != n_tets):
        raise DoseError(f"{path}: the {id_col[0]} ids must list every tet once "
                        f"({ID_COLUMNS[id_col[0]]}…{n_tets - 1 + ID_COLUMNS[id_col[0]]}); "
                        "check the id column and its base")
    value = np.empty(n_tets)
    value[ids.astype(np.int64)] = table[:, 1]
    sigma = None
    if s_col is not None:
        sigma = np.empty(n_tets)
        sigma[ids.astype(np.int64)] = table[:, 2] * (np.abs(table[:, 1]) if s_col == REL_ERR
                                                     else 1.0)
    if not np.all(np.isfinite(value)) or np.any(value < 0) or (
            sigma is not None and (not np.all(np.isfinite(sigma)) or np.any(sigma < 0))):
        raise DoseError(f"{path}: values and uncertainties must be finite and ≥ 0; fix the file")
    return TetTally(kind, value, sigma)


def write_tally_csv(path: str | os.PathLike[str], tally: TetTally) -> Path:
    """Write ``tally`` with a ``tet`` (0-based) column (atomic)."""
    name = {"energy": "energy_mev", "dose": "dose_gy"}[tally.kind]
    cols = [np.arange(len(tally.value)), tally.value]
    header = ["tet", name]
    if tally.sigma is not None:
        cols.append(tally.sigma)
        header.append(QUANTITIES[name][1])
    path = Path(path)
    with atomic_write_file(path) as tmp:
        np.savetxt(tmp, np.column_stack(cols), fmt=["%d"] + ["%.17g"] * (len(cols) - 1),
                   delimiter=",", header=",".join(header), comments="")
    return path
