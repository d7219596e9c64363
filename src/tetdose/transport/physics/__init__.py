"""Interaction physics: material compositions (:mod:`.materials`), the tables built from them
(:mod:`.xs`: photon μ/ρ, μen/ρ), and the sampling kernels of one interaction (:mod:`._photon`).
Electrons sit next to photons here and share the material tables. Kernels here know nothing of
geometry."""
