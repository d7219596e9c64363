"""The plan: what is delivered, before any transport.

Owns the photon sources and treatment (linac) beams (:mod:`.photon_source`, :mod:`.beams`),
energy spectra (:mod:`.spectra`), the prescription (:mod:`.prescription`) and the MU calibration
(:mod:`.mu_calibration`), the :class:`~.model.Plan` that holds them with its TOML reader
(:mod:`.model`), and the DICOM RT Plan reader/writer (:mod:`.rt_plan`). It may import the core,
the DICOM building blocks (:mod:`tetdose.dicom`) and the infrastructure.
"""

from tetdose.plan.model import Plan
from tetdose.plan.photon_source import PhotonSource

__all__ = ["PhotonSource", "Plan"]
