"""ICRP Publication 145 mesh-type phantoms: TetGen ``.node``/``.ele`` and the ``.material`` file.

The mesh-type reference computational phantoms of ICRP Publication 145 (Ann. ICRP 49(3),
2020) come as three text files sharing one stem, read by Geant4's
``examples/advanced/ICRP145_HumanPhantoms`` (``TETModelImport``), by TOPAS-MeshGeom and, after
conversion, by PHITS and MCNP6:

``STEM.node`` (TetGen node file, https://wias-berlin.de/software/tetgen/fformats.node.html)
    first line ``<# points> 3 <# attributes> <# boundary markers>``, then one line per point
    ``<id> <x> <y> <z> [attributes] [marker]``; ids consecutive from 0 or 1. ICRP 145: ids from
    0, no attributes or markers, **coordinates in cm**.
``STEM.ele`` (TetGen element file, .../fformats.ele.html)
    first line ``<# tets> <nodes per tet (4)> <# attributes>``, then
    ``<id> <n1> <n2> <n3> <n4> [attributes]``; ICRP 145: one attribute, the organ/material id.
``STEM.material`` (MCNP material cards with a comment line per material)
    for each material: ``C <name> <density> g/cm3`` then ``m<id>`` followed by pairs
    ``<ZZZ000> -<mass fraction>`` (MCNP ZAID of the natural element and a negative number for a
    mass fraction), as Geant4's ``TETModelImport::MaterialRead`` parses them token by token —
    it ends a material's pairs at a token ``C`` and consumes it, so consecutive materials are
    separated by a lone ``C`` line (read here with or without it).

'#' starts a comment in TetGen files (the format allows it; Geant4's reader does not, so
:mod:`tetdose.coupling.tetgen` never writes one). A tetdose mesh read from such a phantom keeps
the material id as its region label, the material density on the region's own copies of the
vertices (:meth:`TetMesh.split_by_region`: density is constant per material, so each tet's mass
is exactly V·ρ_material) and in cell_data ``density``; tetrahedra are re-oriented (positive
volume) since the format does not fix the vertex order.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tetdose._constants import MM_PER_CM
from tetdose._typing import FloatArray, IntArray
from tetdose.core.composition import Material
from tetdose.core.mesh import TetMesh, compact_points
from tetdose.errors import MeshError

#: File endings of the three files of an ICRP-145-style phantom.
NODE, ELE, MATERIAL = ".node", ".ele", ".material"


@dataclass(frozen=True)
class PhantomMaterial:
    """One entry of a ``.material`` file: name, density [g/cm³], (Z, mass fraction) pairs."""

    id: int
    name: str
    density_g_cm3: float
    mass_fractions: tuple[tuple[int, float], ...]


def stem_of(path: str | os.PathLike[str]) -> Path:
    """``dir/STEM`` of ``dir/STEM.node``, ``.ele``, ``.material`` or of ``dir/STEM`` itself (the
    stem may hold dots: ``phase_050.0.node`` → ``phase_050.0``)."""
    path = Path(path)
    return path.with_suffix("") if path.suffix in (NODE, ELE, MATERIAL) else path


def with_ending(stem: Path, ending: str) -> Path:
    """``dir/STEM`` + ending (``Path.with_suffix`` would replace a dotted stem's last part)."""
    return stem.with_name(stem.name + ending)


def is_icrp145(path: str | os.PathLike[str]) -> bool:
    """True when ``path`` is a ``.node``/``.ele`` file with a ``.material`` file beside it."""
    path = Path(path)
    return path.suffix in (NODE, ELE) and with_ending(stem_of(path), MATERIAL).is_file()


def _data_lines(path: Path) -> list[list[str]]:
    """Whitespace-split lines of ``path`` without comments ('#' to the end of a line)."""
    if not path.is_file():
        raise MeshError(f"{path} does not exist; a TetGen phantom needs STEM.node and STEM.ele "
                        "(and STEM.material for ICRP-145 materials)")
    lines = (ln.split("#", 1)[0].split() for ln in path.read_text(errors="replace").splitlines())
    return [ln for ln in lines if ln]


def _numbers(rows: list[list[str]], count: int, width: int, path: Path, what: str) -> np.ndarray:
    if len(rows) < count:
        raise MeshError(f"{path} announces {count} {what} but holds {len(rows)}; the file is "
                        "truncated — export it again")
    try:
        table = np.array([[float(v) for v in r[:width]] for r in rows[:count]], dtype=np.float64)
    except ValueError as exc:
        raise MeshError(f"{path}: a {what} line is not numeric ({exc}); fix the file") from None
    if table.shape != (count, width):
        raise MeshError(f"{path}: every {what} line needs {width} numbers; fix the file")
    return table


def _header(rows: list[list[str]], path: Path, n: int) -> list[int]:
    try:
        head = [int(v) for v in rows[0][:n]]
    except (IndexError, ValueError):
        head = []
    if len(head) != n:
        raise MeshError(f"{path}: the first line must hold {n} integers (TetGen header); "
                        "this is not a TetGen file")
    return head


def read_tetgen(path: str | os.PathLike[str]) -> tuple[FloatArray, IntArray, IntArray | None]:
    """(points (N, 3) in the file's unit, tets (M, 4) 0-based, first ele attribute or None).

    Node ids may start at 0 or 1 (TetGen allows either; the ``.ele`` refers to the same ids).
    """
    stem = stem_of(path)
    node_path, ele_path = with_ending(stem, NODE), with_ending(stem, ELE)
    rows = _data_lines(node_path)
    n, dim, n_attr, n_mark = _header(rows, node_path, 4)
    if dim != 3 or n < 4:
        raise MeshError(f"{node_path}: header says {n} points in {dim} dimensions; tetdose "
                        "needs 3-D points (header '<n> 3 <attributes> <markers>')")
    nodes = _numbers(rows[1:], n, 4 + n_attr + n_mark, node_path, "point")
    base = int(nodes[0, 0])
    if base not in (0, 1) or np.any(nodes[:, 0] != base + np.arange(n)):
        raise MeshError(f"{node_path}: point ids must run consecutively from 0 or 1; "
                        "renumber the file")
    rows = _data_lines(ele_path)
    m, per_tet, e_attr = _header(rows, ele_path, 3)
    if per_tet not in (4, 10):
        raise MeshError(f"{ele_path}: {per_tet} nodes per tetrahedron; give 4 (linear) or 10")
    ele = _numbers(rows[1:], m, 1 + per_tet + e_attr, ele_path, "tetrahedron")
    tets = ele[:, 1:5].astype(np.int64) - base
    if tets.min() < 0 or tets.max() >= n:
        raise MeshError(f"{ele_path} refers to point ids outside 0…{n - 1} (+{base}); the .ele "
                        "file does not belong to this .node file")
    attr = ele[:, 1 + per_tet].astype(np.int64) if e_attr else None
    return nodes[:, 1:4].copy(), tets, attr


def read_material_file(path: str | os.PathLike[str]) -> dict[int, PhantomMaterial]:
    """Materials of an ICRP-145 ``.material`` file by id (layout in the module docstring)."""
    path = with_ending(stem_of(path), MATERIAL)
    if not path.is_file():
        raise MeshError(f"{path} does not exist; an ICRP-145 phantom needs its material file")
    tokens = path.read_text(errors="replace").split()
    out: dict[int, PhantomMaterial] = {}
    i = 0
    try:
        while i < len(tokens):
            if tokens[i].upper() == "C" and i + 1 < len(tokens) and tokens[i + 1].upper() == "C":
                i += 1  # a lone "C" line between materials
                continue
            if tokens[i].upper() != "C" or not tokens[i + 4].lower().startswith("m"):
                raise ValueError(f"expected 'C NAME DENSITY g/cm3 mID' at token {i + 1}")
            name, rho, mat_id = tokens[i + 1], float(tokens[i + 2]), int(tokens[i + 4][1:])
            i += 5
            pairs = []
            while i < len(tokens) and tokens[i].upper() != "C":
                pairs.append((int(float(tokens[i])) // 1000, abs(float(tokens[i + 1]))))
                i += 2
            if not pairs or rho <= 0 or mat_id in out:
                raise ValueError(f"material m{mat_id} ({name}) has no elements, a density ≤ 0 "
                                 "or a repeated id")
            total = sum(w for _, w in pairs)
            out[mat_id] = PhantomMaterial(mat_id, name, rho,
                                          tuple((z, w / total) for z, w in pairs))
    except (IndexError, ValueError) as exc:
        raise MeshError(f"{path} is not an ICRP-145 material file ({exc}); each material is "
                        "'C NAME DENSITY g/cm3' then 'mID ZZZ000 -FRACTION …'") from None
    return out


def read_icrp145(path: str | os.PathLike[str], *, length_mm: float = MM_PER_CM
                 ) -> tuple[TetMesh, dict[int, PhantomMaterial]]:
    """An ICRP-145-style phantom as a TetMesh [mm] and its materials (module docstring).

    ``length_mm``: millimetres per coordinate unit of the ``.node`` file (10: cm, ICRP 145).
    """
    points, tets, attr = read_tetgen(path)
    materials = read_material_file(path)
    stem = stem_of(path)
    if attr is None:
        raise MeshError(f"{stem}.ele has no region attribute; an ICRP-145 phantom gives each "
                        "tetrahedron its material id as the one attribute")
    unknown = sorted(set(np.unique(attr).tolist()) - set(materials))
    if unknown:
        raise MeshError(f"{stem}.ele uses material ids {unknown[:10]} that {stem}.material "
                        "does not define; add them to the material file")
    points, tets, _ = compact_points(points * float(length_mm), tets)
    rho_of = np.zeros(max(materials) + 1)
    for mat in materials.values():
        rho_of[mat.id] = mat.density_g_cm3
    mesh = TetMesh(points, tets, attr).with_fixed_orientation()
    mesh.check_cells(context=f"in {stem}.ele")
    split = mesh.split_by_region()
    region = np.asarray(split.region)
    rho_point = np.zeros(split.n_points)
    rho_point[split.tets.ravel()] = np.repeat(rho_of[region], 4)
    return split.with_data(point_data={"density": rho_point},
                           cell_data={"density": rho_of[region]}), materials


def phantom_compositions(path: str | os.PathLike[str]
                         ) -> tuple[dict[int, str], dict[str, Material]]:
    """The phantom's own media, for the transport: (material id → name, name → composition)
    from the ``m`` cards of its ``.material`` file (names ``icrp145_<id>_<name>``, nominal
    density the card's). A mesh read from the phantom keeps the id as its region label, so a
    plan's ``[materials]`` and ``compositions`` updated with these give every organ its own
    composition (a plan's own entry for a label wins)."""
    labels: dict[int, str] = {}
    comps: dict[str, Material] = {}
    for mat in read_material_file(path).values():
        name = f"icrp145_{mat.id}_{mat.name}"
        total = sum(w for _, w in mat.mass_fractions)
        fractions = tuple((z, w / total) for z, w in mat.mass_fractions)  # cards round to 1e-3
        comps[name] = Material(name, fractions, mat.density_g_cm3,
                               f"{with_ending(stem_of(path), MATERIAL).name} (ICRP Publication "
                               f"145 phantom material {mat.id})")
        labels[mat.id] = name
    return labels, comps
