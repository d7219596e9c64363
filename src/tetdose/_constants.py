"""Units, tolerances and codes shared by kernels and wrappers. Never mutated (numba freezes globals)."""

MM_PER_CM = 10.0
MM3_PER_CM3 = 1000.0
#: Relative tolerance on geometric predicates (plane side tests), relative to the cell size.
GEOM_TOL_REL = 1e-12
#: Mass density of dry air at sea level [g/cm³] (NIST), the default background outside a mesh.
AIR_DENSITY_G_CM3 = 0.00120479
#: Joules per MeV.
J_PER_MEV = 1.602176634e-13
#: Grams per kilogram.
G_PER_KG = 1000.0
#: keV per MeV (interaction tables list energies in keV).
KEV_PER_MEV = 1000.0
