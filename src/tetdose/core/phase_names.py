"""Phase numbers in file names: pair one-file-per-phase inputs by name, not by argument order.

A list of per-phase files (doses, densities, CTs, displacement fields, phase meshes) whose names
carry the phase — ``20%``, ``phase_020.0``, ``ph2``, or one number where the names otherwise
agree (``dose_0.csv``, ``dose_1.csv``) — is paired with the phases by that number, whatever the
order the shell expanded them in. The numbers are read as phase percentages when they are the
phases' percentages (within :data:`PERCENT_TOL`), else as phase indices 0…K−1 (or 1…K). A list
where only some names carry a number, two names carry the same one, or the numbers are neither
the percentages nor the indices is refused naming the file; names without numbers keep the
given order.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from tetdose.errors import OptionError

_PERCENT = re.compile(r"(\d+(?:\.\d+)?)\s*%")
_PHASE = re.compile(r"(?:phase|ph)[_\- ]?(\d+(?:\.\d+)?)", re.IGNORECASE)
_NUMBER = re.compile(r"\d+(?:\.\d+)?")
#: Largest distance [%] between a percentage in a name and a phase's percentage.
PERCENT_TOL = 0.5
_SUFFIXES = (".nii.gz", ".3ddose.gz")


def stem(path: Path) -> str:
    """The name without its extension (``.nii.gz`` counted as one)."""
    name = path.name
    for suffix in _SUFFIXES:
        if name.lower().endswith(suffix):
            return name[: -len(suffix)]
    return name.rsplit(".", 1)[0] if "." in name and not _NUMBER.fullmatch(name.rsplit(".", 1)[1]
                                                                           ) else name


def name_numbers(paths: Sequence[Path]) -> list[float | None]:
    """The phase number in each name (``%``, ``phase``/``ph`` prefix), else the last number
    when all names are one template differing only there; None where a name says nothing."""
    stems = [stem(Path(p)) for p in paths]
    found: list[float | None] = []
    for s in stems:
        m = _PERCENT.search(s) or _PHASE.search(s)
        found.append(None if m is None else float(m.group(1)))
    if all(f is None for f in found) and len(stems) > 1:
        templates = {_NUMBER.sub("#", s[::-1], count=1)[::-1] for s in stems}
        lasts = [_NUMBER.findall(s) for s in stems]
        if len(templates) == 1 and all(lasts):
            found = [float(n[-1]) for n in lasts]
    return found


_FIX = ("name every file by its phase (phase_020.0, 20%, or the phase index from 0) or none "
        "of them (then they are taken in the given order)")


def _check_numbers(paths: Sequence[Path], numbers: Sequence[float | None], what: str) -> None:
    """OptionError when only some names carry a number, or two carry the same."""
    if any(n is None for n in numbers):
        bare = paths[list(numbers).index(None)]
        named = paths[next(i for i, n in enumerate(numbers) if n is not None)]
        raise OptionError(f"{what}: {bare.name} carries no phase number while {named.name} does; "
                          f"{_FIX}")
    for i, n in enumerate(numbers):
        if n in numbers[:i]:
            raise OptionError(f"{what}: {paths[list(numbers).index(n)].name} and {paths[i].name} "
                              f"both name phase {n:g}; give one file per phase")


def order_by_names(paths: Sequence[Path], percents: Sequence[float], what: str) -> list[Path]:
    """``paths`` in the order of the phases at ``percents`` [%], by the numbers in their names
    (module docstring); the given order when no name carries one. OptionError on contradictions."""
    paths = [Path(p) for p in paths]
    numbers = name_numbers(paths)
    if all(n is None for n in numbers) or len(paths) != len(percents):
        return paths
    _check_numbers(paths, numbers, what)
    pct = np.asarray(percents, dtype=np.float64)
    got = np.asarray(numbers, dtype=np.float64)
    match = np.abs(got[:, None] - pct[None, :]) <= PERCENT_TOL
    if np.all(match.sum(axis=1) == 1) and np.all(match.sum(axis=0) == 1):
        slot = match.argmax(axis=1)
    elif set(numbers) == set(range(len(paths))):
        slot = got.astype(int)
    elif set(numbers) == set(range(1, len(paths) + 1)):  # indices counted from 1
        slot = got.astype(int) - 1
    else:
        stray = next((paths[i].name for i in range(len(paths)) if match[i].sum() != 1), paths[0].name)
        raise OptionError(
            f"{what}: the numbers in the names ({', '.join(f'{n:g}' for n in numbers)}; e.g. "
            f"{stray}) are neither the phases' percentages ({', '.join(f'{p:g}' for p in pct)} "
            f"%) nor their indices 0…{len(paths) - 1}; {_FIX}")
    ordered: list[Path] = [Path()] * len(paths)
    for i, k in enumerate(slot):
        ordered[int(k)] = paths[i]
    return ordered


def percents_from_names(paths: Sequence[Path], what: str) -> tuple[list[Path], list[float] | None]:
    """Files that define the phases (``deform --dvf/--phases``) sorted by the numbers in their
    names, and the phase percentages those say: numbers 0…K−1 are indices (percentages 100·k/K),
    others percentages in [0, 100). ``(paths, None)`` when no name carries a number."""
    paths = [Path(p) for p in paths]
    numbers = name_numbers(paths)
    if all(n is None for n in numbers):
        return paths, None
    _check_numbers(paths, numbers, what)
    k = len(paths)
    if set(numbers) in (set(range(k)), set(range(1, k + 1))):  # indices from 0 or from 1
        return order_by_names(paths, [100.0 * i / k for i in range(k)], what), None
    if any(n is not None and not 0 <= n < 100 for n in numbers):
        bad = next(p for p, n in zip(paths, numbers, strict=True) if n is not None and n >= 100)
        raise OptionError(f"{what}: {bad.name} names phase {name_numbers([bad])[0]:g}, neither a "
                          f"percentage in [0, 100) nor an index 0…{k - 1}; rename the files or "
                          "give --phase-percent")
    pct = sorted(float(n) for n in numbers if n is not None)
    return order_by_names(paths, pct, what), pct
