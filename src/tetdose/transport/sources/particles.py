"""The source particles of a run as arrays: what tetdose's engine starts, for other engines.

:func:`source_particles` draws the particles of histories ``first … first + count − 1`` with the
run's random streams (:mod:`._draw`), so a coupled engine (:mod:`tetdose.coupling.ompmc`) and
tetdose's own transport start from the same particles, history by history.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from tetdose._typing import FloatArray
from tetdose.plan.model import Plan
from tetdose.transport.run.settings import TransportSettings
from tetdose.transport.sources._draw import draw_particles
from tetdose.transport.sources.arrays import source_arrays
from tetdose.transport.sources.quasi import history_points


class SourceParticles(NamedTuple):
    """Source photons: kinetic energy [MeV], start point [mm] and unit direction, (n,) / (n, 3)."""

    energy_mev: FloatArray
    position_mm: FloatArray
    direction: FloatArray


def source_particles(plan: Plan, settings: TransportSettings, first: int, count: int,
                     to_frame: Callable[[FloatArray, bool], FloatArray] | None = None
                     ) -> SourceParticles:
    """The source photons of histories ``first … first + count − 1`` of the run ``settings``
    (seed and stream), in the frame ``to_frame`` gives (as :func:`.arrays.source_arrays`)."""
    src = source_arrays(plan, settings, to_frame)
    energy = np.empty(int(count))
    position = np.empty((int(count), 3))
    direction = np.empty((int(count), 3))
    qmc = history_points(settings.quasi_random, settings.seed, settings.stream,
                         settings.n_histories, settings.n_batches, int(first), int(count))
    draw_particles(src, settings.seed, settings.stream, int(first), qmc, energy, position,
                   direction)
    return SourceParticles(energy, position, direction)
