"""Procedural, seeded phantoms: a CT (HU), its label image and a conforming tetrahedral mesh.

``make_phantom(name, seed=…, size="small"|"medium", **overrides)`` builds one of
:data:`PHANTOMS`:

* ``cube`` — the density-mapping paper's preliminary test: an n×n×n voxel CT crop (n = 3…10)
  of normally distributed HU (``mean_hu``, ``std_hu``) covered exactly by 2×2×1 hexahedra of
  five tetrahedra each (20 tetrahedra, 18 vertices).
* ``liver`` — a deformed superellipsoid organ (≈ 55 HU, mild smooth heterogeneity) in fat and air.
* ``lung`` — parenchyma (≈ −850 HU) with a seeded branching vessel tree (≈ +40 HU) in a body.
* ``thorax`` — body (fat, muscle), both lungs with vessel trees, heart, liver under the right
  lung, a 2.5 cm tumour in the lower right lung, ribs and spine; the demo's phantom.

Meshes come from :func:`mesh_labels` (structured Kuhn grid, no external mesher: staircase
surfaces on exact planes), or with ``mesher="organ"`` from :func:`organ_mesh` (one conforming,
organ-shaped mesh by :func:`tetdose.meshing.conforming_mesh`, extra ``tetdose[meshing]``).
:data:`THORAX_MOVING` selects the thorax's lungs (vessels folded in) and tumour, for a hybrid
world where only what moves is meshed and the rest of the body stays CT voxels. The same seed
gives identical arrays; the seed drives the noise, the heterogeneity and the vessel trees.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from tetdose._atomic import atomic_write_file
from tetdose.core.image import Image
from tetdose.core.io import write_image, write_mesh
from tetdose.core.mesh import TetMesh
from tetdose.errors import TetdoseError
from tetdose.phantoms._builders import BUILDERS
from tetdose.phantoms._meshing import mesh_labels

PHANTOMS: tuple[str, ...] = tuple(BUILDERS)
SIZES: tuple[str, ...] = ("small", "medium")
#: Material names a phantom region may carry (compositions live with the transport code).
MATERIALS: tuple[str, ...] = ("air", "lung", "adipose", "soft_tissue", "muscle",
                              "cortical_bone", "water", "blood")

MESHERS: tuple[str, ...] = ("structured", "organ")
#: Thorax regions that move with breathing: lungs (label 3, vessels 4 folded in) and tumour (6).
THORAX_MOVING: dict[int, tuple[int, ...]] = {3: (3, 4), 6: (6,)}
#: Regions of the organ-shaped meshes (region → labels folded into it), per phantom. Vessel
#: trees (thinner than two voxels in places) are folded into their lung.
ORGAN_REGIONS: dict[str, dict[int, tuple[int, ...]]] = {
    "liver": {2: (2,)},
    "lung": {2: (2, 3)},
    "thorax": THORAX_MOVING,  # what moves; the rest of the body stays CT (the hybrid world)
}

__all__ = ["MATERIALS", "MESHERS", "ORGAN_REGIONS", "PHANTOMS", "SIZES", "THORAX_MOVING",
           "Phantom", "make_phantom", "mesh_labels", "organ_mesh", "write_phantom"]


@dataclass(frozen=True, eq=False)
class Phantom:
    """A phantom: CT [HU], label image, mesh (region = label per tet), names and materials.

    ``label_names`` and ``materials`` map a label (image value and mesh region) to its name and
    to one of :data:`MATERIALS`.
    """

    ct: Image
    labels: Image
    mesh: TetMesh
    label_names: dict[int, str]
    materials: dict[int, str]

    def __post_init__(self) -> None:
        unknown = set(self.materials.values()) - set(MATERIALS)
        if unknown:
            raise TetdoseError(f"unknown material(s) {sorted(unknown)}; use one of {MATERIALS}")
        self.ct.grid.require_same(self.labels.grid, "phantom CT and labels")


def make_phantom(name: str, *, seed: int = 0, size: str = "medium", mesher: str = "structured",
                 **size_params: object) -> Phantom:
    """Build the phantom ``name`` (one of :data:`PHANTOMS`) at ``size`` ("small" for tests).

    ``mesher="organ"`` replaces the structured mesh by :func:`organ_mesh` of
    :data:`ORGAN_REGIONS` (the ``cube`` keeps its 20-tetrahedron mesh).

    ``size_params`` override the preset: ``spacing_mm`` (CT voxel size), ``edge_mm`` (mesh cube
    edge; a cube gives 6 tetrahedra), ``snap_iterations`` (0 = staircase surface); for
    ``cube``: ``n``, ``spacing_mm``, ``mean_hu``, ``std_hu``.
    """
    if name not in BUILDERS:
        raise TetdoseError(f"unknown phantom {name!r}; choose one of {', '.join(PHANTOMS)}")
    if size not in SIZES:
        raise TetdoseError(f"unknown size {size!r}; choose one of {', '.join(SIZES)}")
    builder, presets = BUILDERS[name]
    params = dict(presets[size])
    unknown = set(size_params) - set(params)
    if unknown:
        raise TetdoseError(f"phantom {name!r} takes no parameter(s) {sorted(unknown)}; "
                           f"it accepts {sorted(params)}")
    params.update(size_params)
    if mesher not in MESHERS:
        raise TetdoseError(f"unknown mesher {mesher!r}; choose one of {', '.join(MESHERS)}")
    ct, labels, mesh, names, materials = builder(int(seed), **params)
    phantom = Phantom(ct, labels, mesh, names, materials)
    if mesher == "organ" and name in ORGAN_REGIONS:
        phantom = replace(phantom, mesh=organ_mesh(phantom, ORGAN_REGIONS[name]))
    return phantom


def organ_mesh(phantom: Phantom, regions: Mapping[int, Iterable[int]] | Iterable[int],
               size_mm: float | Mapping[int, float] | None = None) -> TetMesh:
    """One conforming organ-shaped mesh of ``regions`` of the phantom's labels.

    ``regions`` maps a mesh region to the labels it takes (e.g. :data:`THORAX_MOVING`), or lists
    labels meshed as themselves; every other label is outside. ``size_mm``: target edge [mm]
    per region or for all (default from each region's size; see
    :func:`tetdose.meshing.conforming_mesh`).
    """
    from tetdose.meshing import conforming_mesh

    groups = ({int(k): tuple(v) for k, v in regions.items()} if isinstance(regions, Mapping)
              else {int(k): (int(k),) for k in regions})
    arr = np.asarray(phantom.labels.array)
    merged = np.zeros(arr.shape, dtype=np.int32)
    for region, labels in groups.items():
        merged[np.isin(arr, labels)] = region
    return conforming_mesh(phantom.labels.with_array(merged), sorted(groups), size_mm)


def write_phantom(phantom: Phantom, out_dir: str | os.PathLike[str]) -> dict[str, Path]:
    """Write ``ct.nrrd`` (HU), ``labels.nrrd``, ``mesh.vtu`` (cell_data ``region``) and
    ``phantom.json`` (label names and materials) into ``out_dir``; each file atomically."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {
        "ct": write_image(out / "ct.nrrd", phantom.ct),
        "labels": write_image(out / "labels.nrrd", phantom.labels),
        "mesh": write_mesh(out / "mesh.vtu", phantom.mesh),
    }
    info = {
        "labels": {str(k): {"name": v, "material": phantom.materials.get(k)}
                   for k, v in sorted(phantom.label_names.items())},
        "n_tets": phantom.mesh.n_tets,
        "n_points": phantom.mesh.n_points,
        "regions": np.unique(phantom.mesh.region).tolist() if phantom.mesh.region is not None
        else [],
    }
    with atomic_write_file(out / "phantom.json") as tmp:
        tmp.write_text(json.dumps(info, indent=2) + "\n")
    paths["info"] = out / "phantom.json"
    return paths
