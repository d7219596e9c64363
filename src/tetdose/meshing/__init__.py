"""Tetrahedral meshes of segmentations (optional extra ``tetdose[meshing]``).

* :func:`conforming_mesh` (MMG level-set discretisation, :mod:`tetdose.meshing.mmg`): ONE
  conforming mesh of several labels — shared vertices and faces on every interface, one outer
  surface, ``region`` = label, smooth surfaces, a target size per label. The default.
* :func:`mesh_checks` (:mod:`tetdose.meshing.checks`): per-label tets, volume vs voxel volume,
  dihedral angles, surface distance to the label boundary; conformity.
* :func:`mesh_label_image` (:mod:`tetdose.meshing.gmsh`): the older marching cubes + gmsh path,
  one label at a time (touching labels do not conform); kept for single closed surfaces.
* :func:`tetdose.phantoms.mesh_labels`: structured Kuhn grid (staircase, exact planes, no extra).
"""

from tetdose.meshing.checks import conformity, dihedral_angles_deg, mesh_checks
from tetdose.meshing.gmsh import enclosed_volume_mm3, label_surface, mesh_label_image, winding_number
from tetdose.meshing.labels import as_label_array, body_mask, checked_label_ids, default_sizes_mm
from tetdose.meshing.mmg import conforming_mesh

__all__ = ["as_label_array", "body_mask", "checked_label_ids", "conforming_mesh", "conformity",
           "default_sizes_mm", "dihedral_angles_deg", "enclosed_volume_mm3", "label_surface",
           "mesh_checks", "mesh_label_image", "winding_number"]
