"""A volume source: particles born uniformly per unit mass in a region, with isotropic directions.

``plan.toml``::

    [[beam]]
    type = "volume"
    particle = "electron"       # "electron" | "positron" | "photon" (default)
    energy_mev = 1.0            # kinetic energy, or spectrum = (as for beams)
    region = 3                  # optional: a region label (mesh region / label image); default
                                # every cell of the world
    weight = 1.0                # relative weight among all sources

Inside a tetrahedron with linear density the birth points follow that density exactly, in a
voxel they are uniform (:mod:`tetdose.transport.sources._volume`). The dose is per source
particle, as for beams. It is the source of the Fano test and of internal emitters (e.g. a
Y-90 spectrum in the liver, as a spectrum file).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from tetdose.errors import PlanError
from tetdose.plan.photon_source import PARTICLES, check_source_keys
from tetdose.plan.spectra import is_named, named_spectrum, read_spectrum

_KEYS = {"type", "particle", "energy_mev", "spectrum", "region", "weight"}


@dataclass(frozen=True, eq=False)
class VolumeSource:
    """Particles of ``particle`` with energies ``energies_mev`` (lines with ``line_weights``)
    born uniformly per unit mass in region ``region`` (None: the whole world)."""

    particle: str = "photon"
    energies_mev: Sequence[float] = (1.0,)
    line_weights: Sequence[float] = (1.0,)
    region: int | None = None
    weight: float = 1.0

    def __post_init__(self) -> None:
        if self.particle not in PARTICLES:
            raise PlanError(f"volume source particle {self.particle!r} is unknown; use one of "
                            f"{PARTICLES}")
        e = np.asarray(self.energies_mev, dtype=np.float64).reshape(-1)
        wl = np.asarray(self.line_weights, dtype=np.float64).reshape(-1)
        if len(e) == 0 or len(e) != len(wl):
            raise PlanError("a volume source needs at least one energy and one weight per energy")
        if not np.all(np.isfinite(e)) or np.any(e <= 0.0):
            raise PlanError(f"volume source energies must be positive MeV, got {e.tolist()}")
        if not np.all(np.isfinite(wl)) or np.any(wl < 0.0) or wl.sum() <= 0.0:
            raise PlanError("spectrum weights must be non-negative with a positive sum")
        if not (math.isfinite(self.weight) and self.weight > 0.0):
            raise PlanError(f"volume source weight must be positive, got {self.weight}")
        if self.region is not None and (isinstance(self.region, bool)
                                        or int(self.region) != self.region):
            raise PlanError(f"volume source region must be an integer label, got {self.region!r}")
        object.__setattr__(self, "energies_mev", e)
        object.__setattr__(self, "line_weights", wl)
        if self.region is not None:
            object.__setattr__(self, "region", int(self.region))


def volume_source_from_dict(d: Mapping[str, Any], i: int, base_dir: Path) -> VolumeSource:
    """A ``[[beam]] type = "volume"`` table (module docstring) → :class:`VolumeSource`."""
    where = f"beam {i + 1} (volume)"
    check_source_keys(d, _KEYS, where)
    for key in ("energy_mev", "weight"):
        if key in d and (isinstance(d[key], bool) or not isinstance(d[key], int | float)):
            raise PlanError(f"{where}: {key} = {d[key]!r} is not a number; write e.g. "
                            f"{key} = 1.0")
    if "region" in d and (isinstance(d["region"], bool) or not isinstance(d["region"], int)):
        raise PlanError(f"{where}: region = {d['region']!r} is not an integer label; write e.g. "
                        "region = 3")
    if "spectrum" in d and is_named(str(d["spectrum"])):
        energies, weights = named_spectrum(str(d["spectrum"]))
    elif "spectrum" in d:
        energies, weights = read_spectrum(base_dir / d["spectrum"])
    else:
        energies, weights = np.array([float(d["energy_mev"])]), np.ones(1)
    try:
        return VolumeSource(str(d.get("particle", "photon")), energies, weights,
                            d.get("region"), float(d.get("weight", 1.0)))
    except PlanError as exc:
        raise PlanError(f"{where}: {exc}") from None
