"""The dose stage: transport results turned into the doses a physicist reads.

Owns absolute dose (prescription scaling and MU calibration, :mod:`.absolute`), accumulation
over breathing phases on the mesh and on voxels (:mod:`.accumulate`), the 4D dose of a phase
series (:mod:`.dose4d`) and the build-up region marking (:mod:`.buildup`). It may import
transport, motion, mapping, the plan, the core and the infrastructure — never compare, study or
the CLI.
"""
