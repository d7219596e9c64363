"""Named beam qualities: published photon spectra as discrete lines for the source kernel.

- ``"6MV"``, ``"10MV"``, ``"15MV"``: R. Mohan, C. Chui, L. Lidofsky, "Energy and angular
  distributions of photons from medical linear accelerators", Med. Phys. 12(5), 592–597 (1985);
  the bin values as distributed with EGSnrc (``mohan6``, ``mohan10``, ``mohan15`` spectrum
  files), shipped in ``tetdose/data/spectra/mohan*.csv`` with that citation in the header.
- ``"Co60"``: the two ⁶⁰Co γ lines 1.1732 and 1.3325 MeV, equal weights (both ≈ 100 % per
  decay; no capsule or collimator scatter).
- ``"Co60scatter"``: a ⁶⁰Co teletherapy beam on the central axis with the photons scattered in
  the source capsule and the collimators (a third of the photons, 0.05–1.33 MeV): D. W. O.
  Rogers, G. M. Ewart, A. F. Bielajew, G. van Dyk, "Calculation of electron contamination in a
  ⁶⁰Co therapy beam", Proc. IAEA Int. Symp. Dosimetry in Radiotherapy, Vol. 1, 303–312 (1988),
  as distributed with EGSnrc (``co60.spectrum``), shipped in ``rogers_co60.csv``.
- ``"18MV"``: no tabulation with a citable source was found (Mohan et al. 1985 computed one but
  EGSnrc distributes only their 4, 6, 10, 15 and 24 MV spectra), so it is refused with a message
  that says how to give a spectrum file instead.

A histogram bin [e_lo, e_hi] with fluence per MeV φ becomes :data:`LINES_PER_BIN` equal lines at
the sub-bin midpoints, each of weight φ·(e_hi − e_lo)/LINES_PER_BIN: the bin's fluence and mean
energy are exact, the energy resolution is (e_hi − e_lo)/LINES_PER_BIN.

Build-up depth: :data:`DMAX_MM` lists the depth of dose maximum d_max in water for a 10×10 cm²
field at SSD 100 cm, typical textbook values (F. M. Khan, The Physics of Radiation Therapy,
table of d_max by beam quality: Co-60 0.5 cm, 6 MV 1.5 cm, 10 MV 2.5 cm, 15 MV 3.0 cm, 18 MV
3.3 cm), not those of a particular machine. Shallower than d_max there is no charged-particle
equilibrium: tetdose deposits electron energy where the photon interacted (kerma), so there it
reports the kerma, which exceeds the absorbed dose (at the surface by a factor of several).
"""

from __future__ import annotations

import csv
from importlib import resources
from pathlib import Path

import numpy as np

from tetdose._typing import FloatArray
from tetdose.errors import PlanError

#: Energies of the ⁶⁰Co γ lines [MeV].
CO60_LINES_MEV = (1.1732, 1.3325)
#: Lines per histogram bin of a tabulated spectrum.
LINES_PER_BIN = 5
#: Packaged spectrum file per named beam quality.
_FILES = {"6MV": "mohan6.csv", "10MV": "mohan10.csv", "15MV": "mohan15.csv",
          "Co60scatter": "rogers_co60.csv"}
#: Build-up depth d_max in water, 10×10 cm² field [mm] (typical textbook values, see module doc).
DMAX_MM = {"Co60": 5.0, "Co60scatter": 5.0, "6MV": 15.0, "10MV": 25.0, "15MV": 30.0, "18MV": 33.0}
#: Names accepted by :func:`named_spectrum`.
NAMED_SPECTRA = ("6MV", "10MV", "15MV", "18MV", "Co60", "Co60scatter")


def is_named(name: str) -> bool:
    """True for a beam-quality name (``"6MV"``, ``"Co60"``, …; case and ``-``/space ignored)."""
    return canonical_name(name) is not None


def canonical_name(name: str) -> str | None:
    key = str(name).replace(" ", "").replace("-", "").upper()
    for n in NAMED_SPECTRA:
        if n.upper() == key:
            return n
    return None


def named_spectrum(name: str) -> tuple[FloatArray, FloatArray]:
    """(energies [MeV], relative weights) of a named beam quality (see module doc)."""
    canon = canonical_name(name)
    if canon is None:
        raise PlanError(f"spectrum {name!r} is neither a named beam quality {NAMED_SPECTRA} nor "
                        "a .csv file")
    if canon == "Co60":
        return np.array(CO60_LINES_MEV), np.ones(2)
    if canon not in _FILES:
        raise PlanError(f"no citable {canon} spectrum is shipped; give spectrum = \"file.csv\" "
                        "(columns energy_mev, weight, e.g. your linac's commissioned spectrum) "
                        "or use 6MV, 10MV, 15MV, Co60 or Co60scatter")
    return _bins_to_lines(*_read_bins(_FILES[canon]))


def build_up_depth_mm(name: str) -> float:
    """Typical d_max in water [mm] of a named beam quality (see :data:`DMAX_MM`)."""
    canon = canonical_name(name)
    if canon is None:
        raise PlanError(f"{name!r} is not a named beam quality {NAMED_SPECTRA}")
    return DMAX_MM[canon]


def _read_bins(filename: str) -> tuple[FloatArray, FloatArray]:
    text = resources.files("tetdose").joinpath("data", "spectra", filename).read_text()
    rows = list(csv.DictReader(line for line in text.splitlines() if not line.startswith("#")))
    e_high = np.array([float(r["e_high_mev"]) for r in rows])
    per_mev = np.array([float(r["per_mev"]) for r in rows])
    return e_high, per_mev


def _bins_to_lines(e_high_mev: FloatArray, per_mev: FloatArray) -> tuple[FloatArray, FloatArray]:
    e_low = np.concatenate([[0.0], e_high_mev[:-1]])
    width = e_high_mev - e_low
    frac = (np.arange(LINES_PER_BIN) + 0.5) / LINES_PER_BIN
    energies = (e_low[:, None] + width[:, None] * frac[None, :]).reshape(-1)
    weights = np.repeat(per_mev * width / LINES_PER_BIN, LINES_PER_BIN)
    keep = weights > 0.0  # empty bins (e.g. below a spectrum's lowest energy) give no lines
    return energies[keep], weights[keep]


def read_spectrum(path: Path) -> tuple[FloatArray, FloatArray]:
    """Spectrum lines from a CSV with header ``energy_mev,weight``."""
    try:
        with open(path, newline="") as f:
            rows = list(csv.DictReader(f))
    except OSError as exc:
        raise PlanError(f"cannot read spectrum {path}: {exc.strerror}") from exc
    try:
        e = np.array([float(r["energy_mev"]) for r in rows])
        w = np.array([float(r["weight"]) for r in rows])
    except (KeyError, TypeError, ValueError):
        raise PlanError(f"{path}: expected numeric columns energy_mev, weight") from None
    if len(e) == 0:
        raise PlanError(f"spectrum {path} has no rows")
    return e, w
