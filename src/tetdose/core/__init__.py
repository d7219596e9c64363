"""The core: geometry types and the transfers between meshes and grids, used by every stage.

Owns the tetrahedral mesh (:mod:`.mesh`, :mod:`.tetgrid`), the image and its grid
(:mod:`.image`, :mod:`.tilted`), HU → density calibration (:mod:`.calibration`), the body
outline (:mod:`.body`), the exact tetrahedron ∩ voxel overlaps (:mod:`.overlap` and its
kernels), masses (:mod:`.mass`), mesh ↔ grid transfer and point location (:mod:`.transfer`),
exact voxelization of a mesh density (:mod:`.voxelize`) and file I/O of meshes and images
(:mod:`.io`). It may import only the infrastructure (``tetdose._*``, :mod:`tetdose.errors`).
"""
