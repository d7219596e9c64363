"""Beams → the flat source arrays the kernels sample (:mod:`tetdose.transport.sources._sample`).

Dynamic linac segments (:class:`tetdose.plan.segments.DynamicSegment`) keep their control-point
states (angles, jaws, leaves, isocentre) so that the kernel interpolates them per photon; their
geometry enters the source frame through M = F·P, P the patient support → patient matrix of the
patient position and F the linear part of ``to_frame``.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from tetdose._typing import FloatArray
from tetdose.errors import PlanError
from tetdose.plan.beams import support_to_patient
from tetdose.plan.model import Plan
from tetdose.plan.photon_source import SOURCE_KINDS, PhotonSource
from tetdose.plan.segments import DynamicSegment
from tetdose.transport.run.settings import TransportSettings
from tetdose.transport.sources._sample import (
    LINAC,
    LINAC_DYNAMIC,
    PARALLEL,
    PENCIL,
    POINT,
    SourceArrays,
)

#: Highest photon energy the interaction tables cover [MeV].
E_MAX_MEV = 20.0
#: Kernel code of each source kind, keyed by the one spelling of :data:`SOURCE_KINDS`.
_KINDS = dict(zip(SOURCE_KINDS, (PENCIL, PARALLEL, POINT, LINAC), strict=True))
_KINDS[DynamicSegment.kind] = LINAC_DYNAMIC
#: Safety margin on a dynamic segment's largest open area (the rejection bound).
_AREA_MARGIN = 1.0 + 1e-9


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
        **_apertures(beams), **_dynamic(beams, frame))


def _apertures(beams: tuple[PhotonSource | DynamicSegment, ...]) -> dict[str, np.ndarray]:
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


def _dynamic(beams: tuple[PhotonSource | DynamicSegment, ...],
             frame: Callable[[FloatArray, bool], FloatArray]) -> dict[str, np.ndarray]:
    """The ``dyn_*`` arrays of :class:`SourceArrays`: the dynamic segments among ``beams``."""
    segs = [b for b in beams if isinstance(b, DynamicSegment)]
    row = np.full(len(beams), -1, dtype=np.intp)
    row[[i for i, b in enumerate(beams) if isinstance(b, DynamicSegment)]] = np.arange(len(segs))
    mlcs = [(s.start.mlc, s.end.mlc) for s in segs]
    pairs = [0 if a is None else len(a.boundaries_mm) - 1 for a, _ in mlcs]
    ints = lambda v: np.asarray(v, dtype=np.intp).reshape(-1)  # noqa: E731
    flat = lambda v, n: np.asarray(v, dtype=np.float64).reshape(-1, n)  # noqa: E731
    cat = lambda parts: np.concatenate([np.zeros(0), *parts]).astype(np.float64)  # noqa: E731
    out = {
        "row": row,
        "angles": flat([[s.start.gantry_deg, s.start.collimator_deg, s.start.couch_deg,
                         *s.turns_deg] for s in segs], 6),
        "iso": flat([np.concatenate([frame(s.isocenter_start_mm[None], False)[0],
                                     frame(s.isocenter_end_mm[None], False)[0]])
                     for s in segs], 6),
        "jaws": flat([np.concatenate([s.start.jaws_mm, s.end.jaws_mm]) for s in segs], 8),
        "rot": np.ascontiguousarray(
            [frame(support_to_patient(s.patient_position).T, True).T for s in segs],
            dtype=np.float64).reshape(-1, 3, 3),
        "leaf_start": ints(np.cumsum([0, *[2 * n for n in pairs]])[:-1]),
        "n_pairs": ints(pairs),
        "bnd_start": ints(np.cumsum([0, *[n + 1 if n else 0 for n in pairs]])[:-1]),
        "mlc_y": ints([a is not None and a.axis == "Y" for a, _ in mlcs]),
        "leaf0": cat([a.positions_mm for a, _ in mlcs if a is not None]),
        "leaf1": cat([b.positions_mm for _, b in mlcs if b is not None]),
        "bnd": cat([a.boundaries_mm for a, _ in mlcs if a is not None]),
        "max_area": np.asarray([s.max_area_mm2 * _AREA_MARGIN for s in segs], dtype=np.float64)}
    return {f"dyn_{k}": v for k, v in out.items()}
