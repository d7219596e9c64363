"""The coupling layer: tetdose's phases in and out of other transport codes.

Physicists who study motion already trust a transport code (EGSnrc, GATE/Geant4, TOPAS, PHITS,
MCNP6). This layer runs or feeds those codes and brings their doses back onto tetdose's mesh,
where accumulation over the breathing phases happens on the same matter:

- :mod:`.ompmc`: an EGSnrc-physics voxel engine in the box (the pip package ``ompmc``, optional
  extra ``tetdose[ompmc]``): ``simulate_ompmc(density, plan, settings)`` → a
  :class:`~tetdose.transport.history.result.DoseResult` like tetdose's own engine returns;
- :mod:`.onto_mesh`: a voxel dose put on the tetrahedra by energy (dose × voxel mass, split by the
  exact tet ∩ voxel overlaps) over the tet's mass;
- :mod:`.export` (``tetdose export-phases``): phases out to codes that track on tetrahedra, with
  one mass-keeping density per tet binned into materials (:mod:`.binning`), as TetGen/ICRP-145
  (:mod:`.tetgen`) or Abaqus/MCNP6 (:mod:`.abaqus`) files;
- :mod:`.import_dose` (``tetdose import-dose``): their doses back — per-tet tallies
  (:mod:`.tally_csv`), EGSnrc ``.3ddose`` (:mod:`.threeddose`), RT Dose and images
  (:mod:`.dose_files`) — onto the mesh and accumulated over the phases.

It sits above :mod:`tetdose.dose` in the layer order and may import everything below it.
"""

from tetdose.coupling.onto_mesh import voxel_dose_onto_mesh

__all__ = ["voxel_dose_onto_mesh"]
