"""A binned phase as an Abaqus ``.inp`` mesh for MCNP6's unstructured-mesh (UM) geometry.

Written to the MCNP 6.3 user manual, chapter 8.7 ("Abaqus-formatted Mesh Input File"): MCNP
reads only ``*Heading``, ``*Part``/``*End Part``, ``*Node``, ``*Element``, ``*Elset``,
``*Assembly``/``*End Assembly``, ``*Instance``/``*End Instance``, ``*Material`` and
``*Density``, so that is all this writer emits:

* one part ``Part-phase`` with the nodes (ids from 1, coordinates in **cm**, MCNP's length
  unit), one ``*Element, type=C3D4`` block (element k+1 is tetdose tet k, vertices in
  tetdose's positive order, which is Abaqus's: nodes 1-2-3 counter-clockwise seen from node 4)
  and, per material ZZZ, one element set ``Set-material_statistic_ZZZ``. MCNP needs in every
  part a *material* and a *statistic* elset whose names end in ``_ZZZ``; one set may carry
  both keywords (§8.3.1.1: "material_statistic_source_002" is legal), and each becomes one
  pseudo-cell holding one material;
* one assembly with one untransformed instance ``Part-phase-1``;
* per material ``*Material, name=NAME_ZZZ`` (the trailing number is what MCNP matches with the
  elsets; the name avoids the elset keywords) and ``*Density`` with the density [g/cm³].
  MCNP itself ignores ``*Density``; ``um_pre_op -m`` copies it onto the pseudo-cell cards of
  the skeleton input it writes (as given: make it negative, a mass density, in the MCNP input).

The material compositions (elemental mass fractions) go in the MCNP input's ``m`` cards: the
``.material`` file written beside the ``.inp`` by ``tetdose export-phases`` holds them.
"""

from __future__ import annotations

import io
import os
import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from tetdose._atomic import atomic_write_file
from tetdose._constants import MM_PER_CM
from tetdose._typing import FloatArray, IntArray
from tetdose.coupling.binning import BinMaterial
from tetdose.errors import MeshError

PART = "Part-phase"
#: Element ids per ``*Elset`` data line (the manual suggests 16 or fewer).
IDS_PER_LINE = 16
#: Significant digits of the written coordinates [cm].
COORD_DIGITS = 12


def elset_name(material_id: int) -> str:
    return f"Set-material_statistic_{material_id}"


def write_abaqus(path: str | os.PathLike[str], points_mm: FloatArray, tets: IntArray,
                 material_id: IntArray, materials: Sequence[BinMaterial], *,
                 title: str = "tetdose phase") -> Path:
    """Write the ``.inp`` described in the module docstring (atomic)."""
    pts_cm = np.asarray(points_mm, dtype=np.float64) / MM_PER_CM
    tets = np.asarray(tets, dtype=np.int64)
    mat = np.asarray(material_id, dtype=np.int64)
    out = io.StringIO()
    out.write(f"*Heading\n{title}; lengths in cm, densities in g/cm3\n"
              "** written by tetdose for the MCNP6 unstructured mesh (EMBED card)\n"
              f"*Part, name={PART}\n*Node\n")
    np.savetxt(out, np.column_stack([np.arange(1, len(pts_cm) + 1), pts_cm]),
               fmt=["%d"] + [f"%.{COORD_DIGITS}g"] * 3, delimiter=", ")
    out.write("*Element, type=C3D4\n")
    np.savetxt(out, np.column_stack([np.arange(1, len(tets) + 1), tets + 1]), fmt="%d",
               delimiter=", ")
    for m in materials:
        out.write(f"*Elset, elset={elset_name(m.id)}\n")
        ids = np.flatnonzero(mat == m.id) + 1
        for lo in range(0, len(ids), IDS_PER_LINE):
            out.write(", ".join(map(str, ids[lo:lo + IDS_PER_LINE].tolist())) + ",\n")
    out.write(f"*End Part\n**\n*Assembly, name=Assembly\n*Instance, name={PART}-1, part={PART}\n"
              "*End Instance\n*End Assembly\n**\n** MATERIALS\n**\n")
    for m in materials:
        out.write(f"*Material, name={m.name}\n*Density\n{m.density_g_cm3!r},\n")
    path = Path(path)
    with atomic_write_file(path) as tmp:
        tmp.write_text(out.getvalue())
    return path


def read_abaqus(path: str | os.PathLike[str]) -> tuple[FloatArray, IntArray, IntArray,
                                                        dict[int, float]]:
    """(points (N, 3) [cm], tets (M, 4) 0-based in element order, material number per element,
    material number → ``*Density``) of a single-part C3D4 ``.inp`` as written above (or by
    another tool: any ``*Elset`` whose name holds "material" and ends in ``_ZZZ``/``-ZZZ``,
    ``generate`` ranges allowed)."""
    blocks = _blocks(Path(path))
    nodes = np.array([row for key, _, rows in blocks if key == "NODE" for row in rows],
                     dtype=np.float64)
    elems = np.array([row for key, _, rows in blocks if key == "ELEMENT" for row in rows],
                     dtype=np.int64)
    if nodes.ndim != 2 or nodes.shape[1] != 4 or elems.ndim != 2 or elems.shape[1] != 5:
        raise MeshError(f"{path}: needs *Node lines 'id, x, y, z' and *Element, type=C3D4 lines "
                        "'id, n1, n2, n3, n4'")
    tets = _positions(nodes[:, 0].astype(np.int64), elems[:, 1:], f"{path}: an element", "node")
    material = np.zeros(len(elems), dtype=np.int64)
    density: dict[int, float] = {}
    current = None
    for key, params, rows in blocks:
        name = params.get("ELSET") or params.get("NAME") or ""
        number = re.search(r"[_-](\d+)$", name)
        if key == "ELSET" and "material" in name.lower() and number:
            ids = [v for row in rows for v in row]
            if "GENERATE" in params:
                ids = list(range(int(ids[0]), int(ids[1]) + 1, int(ids[2])))
            at = _positions(elems[:, 0], np.asarray(ids, dtype=np.int64), f"{path}: {name}",
                            "element")
            material[at] = int(number.group(1))
        elif key == "MATERIAL":
            current = int(number.group(1)) if number else None
        elif key == "DENSITY" and current is not None and rows:
            density[current] = float(rows[0][0])
    return nodes[:, 1:], tets, material, density


def _positions(ids: IntArray, wanted: IntArray, who: str, what: str) -> IntArray:
    """Row of each of ``wanted`` in the id list ``ids``; an unknown id is a :class:`MeshError`."""
    order = np.argsort(ids, kind="stable")
    at = np.searchsorted(ids[order], wanted).clip(0, len(ids) - 1)
    found = ids[order][at] == wanted
    if not np.all(found):
        raise MeshError(f"{who} refers to {what} {int(np.asarray(wanted)[~found][0])}, which is "
                        "not defined; the file is inconsistent")
    return order[at]


def _blocks(path: Path) -> list[tuple[str, dict[str, str], list[list[float]]]]:
    """(keyword, parameters, numeric data rows) of each ``*KEYWORD`` block; comments skipped."""
    if not path.is_file():
        raise MeshError(f"{path} does not exist; give the .inp file written by export-phases")
    blocks: list[tuple[str, dict[str, str], list[list[float]]]] = []
    for line in path.read_text(errors="replace").splitlines():
        if line.startswith("**") or not line.strip():
            continue
        if line.startswith("*"):
            key, *params = [p.strip() for p in line[1:].split(",")]
            pmap = {p.split("=")[0].strip().upper(): p.partition("=")[2].strip() for p in params}
            blocks.append((key.upper(), pmap, []))
        elif blocks:
            try:
                blocks[-1][2].append([float(v) for v in line.split(",") if v.strip()])
            except ValueError:
                continue  # a text data line (the *Heading title)
    return blocks
