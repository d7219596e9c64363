"""The coupling layer: tetdose's breathing geometry in and out of other transport codes (issue 21).

Phases out to codes that track on tetrahedra (:mod:`tetdose.coupling.export`: TetGen/ICRP-145
and Abaqus files with binned materials), their doses back onto the mesh and accumulated
(:mod:`tetdose.coupling.import_dose`).
"""
