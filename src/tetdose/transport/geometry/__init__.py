"""Transport geometry: the worlds particles walk and the kernels that walk them.

Owns the tetrahedral walker (:mod:`._tet`: exit faces, neighbour links, linear density, entry
ray cast; :mod:`._prefetch`), the voxel walker (:mod:`._voxel`, Amanatides–Woo), the hybrid world
(:mod:`._world`: mesh ↔ voxel switches, vacuum flights), their array builders (:mod:`.tets`)
and the :class:`~.world.World` model object. Kernels here know nothing of particles or physics.
"""

from tetdose.transport.geometry.tets import mesh_geometry, morton_order

__all__ = ["mesh_geometry", "morton_order"]
