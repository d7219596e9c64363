"""A binned phase as an ICRP-145-style phantom: TetGen ``.node``/``.ele`` and a ``.material`` file.

The layout is that of the ICRP Publication 145 mesh phantoms as Geant4's
``ICRP145_HumanPhantoms`` example (``TETModelImport``) and TOPAS-MeshGeom read them (see
:mod:`tetdose.core.icrp145` for the format and the reader):

* ``STEM.node``: ``N 3 0 0``, then ``id x y z`` with ids from 0 and coordinates in **cm**
  (Geant4 multiplies them by ``cm``); no comment lines (Geant4's reader does not skip them);
* ``STEM.ele``: ``M 4 1``, then ``id n1 n2 n3 n4 material`` with 0-based node ids and the
  1-based material id as the one region attribute (Geant4 indexes its vertex vector with the
  node ids directly, so they must start at 0);
* ``STEM.material``: per material ``C NAME DENSITY g/cm3`` then ``mID ZZZ000 -w`` with one
  element per line (MCNP material-card syntax: mass fractions negative, continuation lines
  indented by 5 spaces; a lone ``C`` line between materials, see :func:`material_cards`), so
  the file also pastes into an MCNP or PHITS input.

Vertices keep tetdose's positive orientation (det[b − a, c − a, d − a] > 0).
"""

from __future__ import annotations

import io
import os
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from tetdose._atomic import atomic_write_file
from tetdose._constants import MM_PER_CM
from tetdose._typing import FloatArray, IntArray
from tetdose.core.icrp145 import (
    ELE,
    MATERIAL,
    NODE,
    PhantomMaterial,
    read_icrp145,
    read_material_file,
    read_tetgen,
    with_ending,
)
from tetdose.coupling.binning import BinMaterial
from tetdose.transport.physics.materials import MATERIALS, Material

__all__ = ["read_icrp145", "read_material_file", "read_tetgen", "write_material_file",
           "write_tetgen", "PhantomMaterial"]

#: Significant digits of the written coordinates [cm] (sub-nm on a body; volumes to ~1e-11).
COORD_DIGITS = 12


def material_cards(materials: Sequence[BinMaterial],
                   library: Mapping[str, Material] | None = None) -> str:
    """The ``.material`` text: ``C NAME DENSITY g/cm3`` and an MCNP ``m`` card per material,
    consecutive materials separated by a line ``C`` alone; compositions by name from
    ``library`` (default :data:`MATERIALS`).

    The separator is what Geant4's token reader needs: it ends a material's element list at
    the first token ``C`` (consuming it) and then reads ``C NAME DENSITY g/cm3 mID`` — so each
    further header needs one more ``C`` before it, and none may follow the last material.
    """
    out = io.StringIO()
    for k, m in enumerate(materials):
        out.write(f"{'C' + chr(10) if k else ''}C {m.name} {m.density_g_cm3!r} g/cm3\n")
        mat = (library or MATERIALS)[m.composition]
        for i, (z, w) in enumerate(zip(mat.elements, mat.weights, strict=True)):
            lead = f"m{m.id}" if i == 0 else ""
            out.write(f"{lead:<5}{int(z) * 1000} {-w:.6f}\n")
    return out.getvalue()


def write_material_file(path: str | os.PathLike[str], materials: Sequence[BinMaterial],
                        library: Mapping[str, Material] | None = None) -> Path:
    """Write ``STEM.material`` (atomic; ``library`` as for :func:`material_cards`)."""
    path = Path(path)
    with atomic_write_file(path) as tmp:
        tmp.write_text(material_cards(materials, library))
    return path


def write_tetgen(stem: str | os.PathLike[str], points_mm: FloatArray, tets: IntArray,
                 material_id: IntArray, materials: Sequence[BinMaterial],
                 library: Mapping[str, Material] | None = None) -> list[Path]:
    """Write ``STEM.node`` (cm), ``STEM.ele`` (0-based, material id attribute) and
    ``STEM.material``; each file atomic. Returns the three paths."""
    stem = Path(stem)
    pts_cm = np.asarray(points_mm, dtype=np.float64) / MM_PER_CM
    tets = np.asarray(tets, dtype=np.int64)
    node = np.column_stack([np.arange(len(pts_cm)), pts_cm])
    ele = np.column_stack([np.arange(len(tets)), tets, np.asarray(material_id, np.int64)])
    paths = [with_ending(stem, NODE), with_ending(stem, ELE)]
    for path, header, table, fmt in (
            (paths[0], f"{len(node)} 3 0 0", node, ["%d"] + [f"%.{COORD_DIGITS}g"] * 3),
            (paths[1], f"{len(ele)} 4 1", ele, "%d")):
        with atomic_write_file(path) as tmp:
            np.savetxt(tmp, table, fmt=fmt, header=header, comments="")
    return [*paths, write_material_file(with_ending(stem, MATERIAL), materials, library)]
