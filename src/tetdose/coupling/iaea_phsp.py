"""IAEA phase-space files: particles handed to other transport codes, one per history.

The format is that of R. Capote, R. Jeraj, C.-M. Ma, D. W. O. Rogers, F. Sánchez-Doblado,
J. Sempau, J. Seuntjens, J. V. Siebers, "Phase-space database for external beam radiotherapy",
IAEA report INDC(NDS)-0484 (2006): a pair of files sharing a base name, an ASCII
``base.IAEAheader`` of ``$KEYWORD:`` blocks and a binary ``base.IAEAphsp`` of fixed-length
little-endian records. Each record written here is (29 bytes)

    int8 type (1 photon, 2 electron, 3 positron; negative when the direction cosine w < 0),
    float32 E [MeV, kinetic; negative marks the first particle of a new history],
    float32 x, y, z [cm], float32 u, v (w = ±√(1 − u² − v²) is not stored), float32 weight.

``$RECORD_CONTENTS:`` lists the flags of x, y, z, u, v, w, weight (1 = stored per particle),
then the numbers of extra floats and extra longs (0 and 0 here). ompmc (:mod:`.ompmc`), EGSnrc,
Geant4's G4IAEAphsp reader, PENELOPE and TOPAS read it. Every particle written here starts a
history of its own (tetdose's source draws one particle per history).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import NamedTuple

import numpy as np

from tetdose._atomic import atomic_write_file
from tetdose._typing import FloatArray, IntArray
from tetdose.errors import TetdoseError

#: IAEA particle type codes.
PHOTON, ELECTRON, POSITRON = 1, 2, 3
HEADER_SUFFIX, DATA_SUFFIX = ".IAEAheader", ".IAEAphsp"
#: The record layout written (and read) here.
RECORD = np.dtype([("type", "i1"), ("energy", "<f4"), ("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                   ("u", "<f4"), ("v", "<f4"), ("weight", "<f4")])


class PhaseSpace(NamedTuple):
    """Particles of a phase space: type code, kinetic energy [MeV], position [cm], direction,
    statistical weight, and whether each starts a new history."""

    particle: IntArray
    energy_mev: FloatArray
    position_cm: FloatArray
    direction: FloatArray
    weight: FloatArray
    new_history: np.ndarray


def paths(base: str | os.PathLike[str]) -> tuple[Path, Path]:
    """(header, data) paths of the phase space with base name ``base``."""
    base = Path(base)
    for suffix in (HEADER_SUFFIX, DATA_SUFFIX):
        if base.name.endswith(suffix):
            base = base.with_name(base.name[:-len(suffix)])
    return base.with_name(base.name + HEADER_SUFFIX), base.with_name(base.name + DATA_SUFFIX)


def write_phase_space(base: str | os.PathLike[str], energy_mev: FloatArray,
                      position_cm: FloatArray, direction: FloatArray,
                      weight: FloatArray | None = None, particle: int | IntArray = PHOTON, *,
                      title: str = "tetdose source particles") -> tuple[Path, Path]:
    """Write ``base.IAEAheader`` and ``base.IAEAphsp`` (atomically), one history per particle.

    ``direction`` rows are unit vectors; ``weight`` defaults to 1. Returns (header, data) paths.
    """
    e = np.asarray(energy_mev, dtype=np.float64).reshape(-1)
    n = len(e)
    pos = np.asarray(position_cm, dtype=np.float64).reshape(n, 3)
    d = np.asarray(direction, dtype=np.float64).reshape(n, 3)
    wt = np.ones(n) if weight is None else np.asarray(weight, dtype=np.float64).reshape(n)
    kind = np.broadcast_to(np.asarray(particle, dtype=np.int8), (n,))
    if n == 0:
        raise TetdoseError("a phase space needs at least one particle")
    if not (np.all(np.isfinite(e)) and np.all(e > 0) and np.all(np.isfinite(pos))
            and np.all(np.isfinite(wt)) and np.all(wt >= 0)):
        raise TetdoseError("phase-space particles need positive energies, finite positions and "
                           "non-negative weights")
    if np.abs(np.einsum("ij,ij->i", d, d) - 1.0).max() > 1e-9:
        raise TetdoseError("phase-space directions must be unit vectors")
    if not np.all(np.isin(kind, (PHOTON, ELECTRON, POSITRON))):
        raise TetdoseError("phase-space particle codes are 1 (photon), 2 (electron), 3 (positron)")
    rec = np.empty(n, RECORD)
    rec["type"] = np.where(d[:, 2] < 0.0, -kind, kind)
    rec["energy"] = -e  # every particle starts a history of its own
    rec["x"], rec["y"], rec["z"] = pos.T
    rec["u"], rec["v"] = d[:, 0], d[:, 1]
    rec["weight"] = wt
    counts = {code: int(np.sum(kind == code)) for code in (PHOTON, ELECTRON, POSITRON)}
    header = "\n".join([
        "$IAEA_INDEX:", "0", "$TITLE:", title, "$FILE_TYPE:", "0",
        "$CHECKSUM:", str(n * RECORD.itemsize),
        "$RECORD_CONTENTS:", "1 // X is stored ?", "1 // Y is stored ?", "1 // Z is stored ?",
        "1 // U is stored ?", "1 // V is stored ?", "1 // W is stored ?",
        "1 // Weight is stored ?", "0 // Extra floats stored ?", "0 // Extra longs stored ?",
        "$RECORD_CONSTANT:", "$RECORD_LENGTH:", str(RECORD.itemsize), "$BYTE_ORDER:", "1234",
        "$ORIG_HISTORIES:", str(n), "$PARTICLES:", str(n),
        "$PHOTONS:", str(counts[PHOTON]), "$ELECTRONS:", str(counts[ELECTRON]),
        "$POSITRONS:", str(counts[POSITRON]), ""])
    head, data = paths(base)
    with atomic_write_file(data) as tmp:
        rec.tofile(tmp)
    with atomic_write_file(head) as tmp:
        tmp.write_text(header)
    return head, data


def read_phase_space(base: str | os.PathLike[str]) -> PhaseSpace:
    """Read a phase space written by :func:`write_phase_space` (all seven quantities stored,
    no extras); other layouts are refused with the reason."""
    head, data = paths(base)
    try:
        lines = [ln.split("//")[0].strip() for ln in head.read_text().splitlines()]
    except OSError as exc:
        raise TetdoseError(f"cannot read the phase-space header {head}: {exc.strerror}") from exc
    blocks: dict[str, list[str]] = {}
    key = None
    for ln in lines:
        if ln.startswith("$") and ln.endswith(":"):
            key = ln[1:-1]
            blocks[key] = []
        elif ln and key is not None:
            blocks[key].append(ln)
    contents = [int(v) for v in blocks.get("RECORD_CONTENTS", [])]
    if (contents[:9] != [1, 1, 1, 1, 1, 1, 1, 0, 0] or blocks.get("BYTE_ORDER") != ["1234"]
            or int(blocks.get("RECORD_LENGTH", ["0"])[0]) != RECORD.itemsize):
        raise TetdoseError(f"{head} is not a layout tetdose reads (all of x y z u v w weight "
                           "stored, no extras, little endian, 29-byte records)")
    rec = np.fromfile(data, dtype=RECORD)
    kind = rec["type"].astype(np.int64)
    u, v = rec["u"].astype(np.float64), rec["v"].astype(np.float64)
    w = np.sign(kind) * np.sqrt(np.clip(1.0 - u * u - v * v, 0.0, None))
    pos = np.stack([rec["x"], rec["y"], rec["z"]], axis=1).astype(np.float64)
    return PhaseSpace(np.abs(kind), np.abs(rec["energy"].astype(np.float64)), pos,
                      np.stack([u, v, w], axis=1), rec["weight"].astype(np.float64),
                      rec["energy"] < 0)
