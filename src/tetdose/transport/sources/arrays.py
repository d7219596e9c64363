"""Beams → the flat source arrays the kernels sample (:mod:`tetdose.transport.sources._sample`)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from tetdose._typing import FloatArray
from tetdose.errors import PlanError
from tetdose.plan.model import Plan
from tetdose.plan.photon_source import SOURCE_KINDS, PhotonSource
from tetdose.transport.run.settings import TransportSettings
from tetdose.transport.sources._sample import LINAC, PARALLEL, PENCIL, POINT, SourceArrays

#: Highest photon energy the interaction tables cover [MeV].
E_MAX_MEV = 20.0
#: Kernel code of each source kind, keyed by the one spelling of :data:`SOURCE_KINDS`.
_KINDS = dict(zip(SOURCE_KINDS, (PENCIL, PARALLEL, POINT, LINAC), strict=True))


def source_arrays(plan: Plan, settings: TransportSettings,
                  to_frame: Callable[[FloatArray, bool], FloatArray] | None = None
                  ) -> SourceArrays:
    """Flatten the beams (optionally into a grid frame: ``to_frame(points, is_direction)``).

    Linac apertures stay in beam coordinates (along e1, e2), which a rigid ``to_frame`` keeps.
    """
    plan.require_resolved()
    beams = plan.sources
    for b in beams:
        e = np.asarray(b.energies_mev)
        if e.max() > E_MAX_MEV or e.min() < settings.energy_cutoff_mev:
            raise PlanError(f"beam energies must lie between the cut-off "
                            f"{settings.energy_cutoff_mev} MeV and {E_MAX_MEV} MeV, got "
                            f"{e.min():g}…{e.max():g} MeV")
    frame = to_frame or (lambda a, _is_dir: a)
    vec = lambda attr, is_dir: np.ascontiguousarray(  # noqa: E731
        frame(np.array([getattr(b, attr) for b in beams]), is_dir), dtype=np.float64)
    w = np.array([b.weight for b in beams])
    lines = [np.asarray(b.line_weights) / np.sum(b.line_weights) for b in beams]
    return SourceArrays(
        kind=np.array([_KINDS[b.kind] for b in beams], dtype=np.intp),
        pos=vec("position_mm", False), axis=vec("direction", True), e1=vec("e1", True),
        e2=vec("e2", True), field=np.array([b.field_mm for b in beams], dtype=np.float64),
        cos_half=np.cos(np.radians([b.half_angle_deg for b in beams])),
        beam_cdf=np.cumsum(w) / w.sum(),
        spec_start=np.concatenate([[0], np.cumsum([len(x) for x in lines])]).astype(np.intp),
        spec_energy=np.concatenate([b.energies_mev for b in beams]).astype(np.float64),
        spec_cdf=np.concatenate([np.cumsum(x) for x in lines]).astype(np.float64),
        **_apertures(beams))


def _apertures(beams: tuple[PhotonSource, ...]) -> dict[str, np.ndarray]:
    """sad, rect_start, rect, rect_cdf (by area within each beam) of the linac beams."""
    rects = [b.aperture_mm if b.kind == "linac" else np.zeros((0, 4)) for b in beams]
    cdfs = []
    for r in rects:
        area = (r[:, 1] - r[:, 0]) * (r[:, 3] - r[:, 2])
        cdfs.append(np.cumsum(area) / area.sum() if len(r) else area)
    return {"sad": np.array([b.sad_mm for b in beams], dtype=np.float64),
            "rect_start": np.concatenate([[0], np.cumsum([len(r) for r in rects])]).astype(np.intp),
            "rect": np.ascontiguousarray(np.concatenate(rects), dtype=np.float64).reshape(-1, 4),
            "rect_cdf": np.concatenate(cdfs).astype(np.float64)}
