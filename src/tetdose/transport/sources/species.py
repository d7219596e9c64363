"""Sources of dose mode: the plan's beams grouped by particle species, and its volume sources.

The kernel (:mod:`tetdose.transport.run._dose_batches`) first draws a group with the cumulative
probabilities ``group_cdf`` (photon beams, electron beams, positron beams, volume sources; each in
proportion to the sum of its sources' weights), then a source within it as the beam sampler or
the volume sampler does. Each beam group is flattened by :func:`~.arrays.source_arrays` (an
empty group gets a placeholder beam it never draws).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import replace
from types import SimpleNamespace
from typing import NamedTuple

import numpy as np

from tetdose._typing import FloatArray
from tetdose.errors import PlanError
from tetdose.plan.model import Plan
from tetdose.plan.photon_source import PhotonSource
from tetdose.transport.run.settings import TransportSettings
from tetdose.transport.sources._sample import SourceArrays
from tetdose.transport.sources._volume import VolumeArrays
from tetdose.transport.sources.arrays import E_MAX_MEV, source_arrays

#: Order of the groups in ``group_cdf``.
GROUPS = ("photon", "electron", "positron", "volume")


class ParticleSources(NamedTuple):
    """Dose-mode sources besides the photon beams (which stay the job's ``src``)."""

    electron: SourceArrays
    positron: SourceArrays
    volume: VolumeArrays
    group_cdf: FloatArray  # (4,) cumulative group probability, in the order of GROUPS


def _group_arrays(beams: Sequence[object], plan: Plan, settings: TransportSettings,
                  to_frame: Callable[[FloatArray, bool], FloatArray] | None) -> SourceArrays:
    if not beams:
        beams = (PhotonSource("pencil", (0.0, 0.0, 0.0), energies_mev=(E_MAX_MEV,)),)  # never drawn
    view = SimpleNamespace(sources=tuple(beams), require_resolved=plan.require_resolved)
    return source_arrays(view, settings, to_frame)  # type: ignore[arg-type]


def _particle(source: object) -> str:
    """A source's particle (linac segments, static or dynamic, emit photons)."""
    return str(getattr(source, "particle", "photon"))


def refuse_in_kerma_mode(plan: Plan) -> None:
    """PlanError for electron/positron beams or volume sources in a kerma-mode run."""
    charged = [_particle(b) for b in plan.sources if _particle(b) != "photon"]
    if charged or plan.volume_sources:
        what = f"{charged[0]} beams" if charged else "volume sources"
        raise PlanError(f"{what} need physics 'dose' (electron transport); kerma mode follows "
                        "photons only")


def particle_sources(plan: Plan, settings: TransportSettings,
                     to_frame: Callable[[FloatArray, bool], FloatArray] | None,
                     volume: VolumeArrays) -> tuple[SourceArrays, ParticleSources]:
    """(photon beam arrays, the other groups) of ``plan`` in the world's frame."""
    plan.require_resolved()
    for v in plan.volume_sources:
        cut = settings.energy_cutoff_mev if v.particle == "photon" else 0.0
        if max(v.energies_mev) > E_MAX_MEV or min(v.energies_mev) < cut:
            raise PlanError(f"volume source energies must lie between {cut:g} MeV (the photon "
                            f"cut-off for photons) and {E_MAX_MEV} MeV, got "
                            f"{min(v.energies_mev):g}…{max(v.energies_mev):g} MeV")
    by = {p: [b for b in plan.sources if _particle(b) == p] for p in GROUPS[:3]}
    weights = [sum(b.weight for b in by[p]) for p in GROUPS[:3]]
    weights.append(sum(v.weight for v in plan.volume_sources))
    charged = replace(settings, energy_cutoff_mev=settings.electron_cutoff_mev)
    photon = _group_arrays(by["photon"], plan, settings, to_frame)
    electron = _group_arrays(by["electron"], plan, charged, to_frame)
    positron = _group_arrays(by["positron"], plan, charged, to_frame)
    w = np.asarray(weights, dtype=np.float64)
    cdf = np.cumsum(w) / w.sum()
    cdf[-1] = 1.0
    return photon, ParticleSources(electron, positron, volume, cdf)


def source_mix(plan: Plan) -> dict[str, object] | None:
    """How a plan with volume sources (or e± beams) shares its source particles between groups,
    for the run record; None for photon beams alone.

    One draw per history: group g with probability W_g / Σ W (W_g the sum of its sources'
    ``weight``), then a source within it. A linac beam's weight is its meterset (MU), so a volume
    source of weight w next to beams of M MU gets w / (M + w) of the histories; the dose is per
    source particle of the whole mix, and a prescription or normalisation scales all groups by
    one factor.
    """
    by = {p: [b for b in plan.sources if _particle(b) == p] for p in GROUPS[:3]}
    weights = [sum(b.weight for b in by[p]) for p in GROUPS[:3]]
    weights.append(sum(v.weight for v in plan.volume_sources))
    if not any(weights[1:]):
        return None
    total = sum(weights)
    return {"fraction_of_histories": {g: w / total for g, w in zip(GROUPS, weights, strict=True)},
            "weights": dict(zip(GROUPS, weights, strict=True)),
            "rule": "each history draws a source with probability weight / sum of weights (a "
                    "linac beam's weight is its MU); dose per source particle of the whole mix"}
