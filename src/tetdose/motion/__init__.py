"""Breathing motion: phase meshes, motion sources and the mass-conserving density update.

Motion sources: phase meshes (:class:`PhaseSeries`), displacement-field images
(:mod:`~tetdose.motion.dvf`), surface-driven linear-elastic FEM (:mod:`~tetdose.motion.fem`,
extra ``tetdose[fem]``) and the built-in Lujan breathing model (:class:`BreathingModel`).
One series from the source a user names: :func:`phase_series` (:mod:`~tetdose.motion.source`).
Densities per phase: :func:`update_series` (:mod:`~tetdose.motion.conserve`); 4D virtual CT:
:mod:`~tetdose.motion.ct4d`.
"""

from tetdose.motion.breathing import BreathingModel
from tetdose.motion.conserve import PhaseReport, update_density, update_series
from tetdose.motion.dvf import DisplacementField, read_dvf
from tetdose.motion.phases import PhaseSeries
from tetdose.motion.source import mass_report_csv, phase_series

__all__ = [
    "BreathingModel",
    "DisplacementField",
    "PhaseReport",
    "PhaseSeries",
    "mass_report_csv",
    "phase_series",
    "read_dvf",
    "update_density",
    "update_series",
]
