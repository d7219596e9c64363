"""CT voxels → elemental compositions: Schneider's HU bins (default) or the five density classes.

Schneider, Bortfeld & Schlegel (Phys. Med. Biol. 45:459, 2000, Table 6) give 24 HU intervals,
each with one elemental composition: air (< −950 HU), lung (−950…−120), five adipose/adrenal/
small-intestine mixtures (−120…19), soft tissue (19…80), connective tissue (80…120) and fifteen
marrow/bone mixtures (120…1500 HU and above), the method of GATE, TOPAS and EGSnrc's ctcreate.
The table ships in ``tetdose/data/schneider2000_compositions.json`` (GATE's tabulation; its two
added rows, amalgam and metal, are left out: label implants as regions with their own material).
The HU → density curve stays the user's calibration (:mod:`tetdose.core.calibration`): the bins
choose the composition only; each bin's nominal density (of its density effect) is the
calibration's density at the bin's middle HU (−1000 HU for air, 1550 HU for the last bin).

:func:`schneider_labels` turns a CT into labels: voxels that no plan region claims get label
:data:`FIRST_LABEL` + bin, with a material named ``schneider_<bin name>`` per label; the
transport then gives them those compositions like any ``[materials]`` region. The other rule,
``density-classes``, leaves them to the five density classes of
:mod:`tetdose.transport.physics.materials` (air, lung, adipose, soft tissue, cortical bone).
"""

from __future__ import annotations

import json
from collections.abc import Collection
from functools import cache
from importlib import resources

import numpy as np

from tetdose.core.calibration import HUCalibration
from tetdose.core.composition import Material, material_from_symbols
from tetdose.core.image import Image
from tetdose.errors import OptionError

#: The rules for CT voxels outside the plan's regions (``--ct-materials``), default first.
CT_MATERIAL_RULES = ("schneider", "density-classes")
#: Label of the first Schneider bin (bins get FIRST_LABEL … FIRST_LABEL + 23).
FIRST_LABEL = 100_000
#: HU of the open ends of the first and last bins, for their nominal densities.
_END_HU = (-1000.0, 1550.0)


@cache
def _table() -> tuple[str, tuple[float, ...], tuple[tuple[str, dict[str, float]], ...]]:
    text = resources.files("tetdose").joinpath("data", "schneider2000_compositions.json")
    raw = json.loads(text.read_text())
    bins = raw["bins"]
    return (raw["citation"], tuple(float(b["hu_min"]) for b in bins),
            tuple((b["name"], {s: v / 100.0 for s, v in b["percent"].items()}) for b in bins))


def schneider_bin(hu: np.ndarray) -> np.ndarray:
    """Index of Schneider's bin of each CT number [HU] (intp; below the first bin's lower
    bound: bin 0, air)."""
    _, lows, _ = _table()
    return np.maximum(np.searchsorted(np.array(lows), np.asarray(hu, dtype=np.float64),
                                      side="right") - 1, 0).astype(np.intp)


def schneider_materials(calibration: HUCalibration) -> list[Material]:
    """The bins' compositions as materials ``schneider_<name>``, nominal density from
    ``calibration`` at each bin's middle HU (module docstring)."""
    citation, lows, rows = _table()
    edges = [*lows[1:], 2 * _END_HU[1] - lows[-1]]
    out = []
    for k, (name, fractions) in enumerate(rows):
        mid = _END_HU[0] if k == 0 else 0.5 * (lows[k] + edges[k])
        rho = max(float(calibration.density(mid)), 1e-4)
        out.append(material_from_symbols(f"schneider_{name.lower()}", fractions, rho,
                                         f"{citation} HU ≥ {lows[k]:g}"))
    return out


def schneider_labels(ct_hu: Image, calibration: HUCalibration, labels: Image | None,
                     claimed: Collection[int]) -> tuple[Image, dict[int, str],
                                                        dict[str, Material]]:
    """(label image, label → material name, name → Material): voxels whose label is not in
    ``claimed`` (the plan's ``[materials]`` labels; all voxels without ``labels``) get
    :data:`FIRST_LABEL` + their Schneider bin; only the bins used are returned."""
    hu = np.asarray(ct_hu.array)
    lab = (np.zeros(hu.shape, np.int64) if labels is None
           else np.asarray(labels.array).astype(np.int64))
    if labels is not None:
        ct_hu.grid.require_same(labels.grid, "the CT and the label image")
        if np.any(lab >= FIRST_LABEL):
            raise OptionError(f"label image values ≥ {FIRST_LABEL} are reserved for Schneider's "
                              "HU bins; renumber the labels or use --ct-materials "
                              "density-classes")
    free = ~np.isin(lab, np.fromiter(claimed, np.int64))
    bins = schneider_bin(hu)
    lab = np.where(free, FIRST_LABEL + bins, lab)
    mats = schneider_materials(calibration)
    used = np.unique(bins[free])
    names = {FIRST_LABEL + int(k): mats[k].name for k in used}
    return (Image(lab.astype(np.int64), ct_hu.grid), names,
            {mats[k].name: mats[k] for k in used})


def assignment_record(labels: Image, names: dict[int, str]) -> dict[str, object]:
    """For run records: the rule, its citation and the voxels of each Schneider bin."""
    citation, _, _ = _table()
    lab = np.asarray(labels.array)
    return {"rule": "schneider", "citation": citation,
            "voxels": {names[k]: int(np.count_nonzero(lab == k)) for k in sorted(names)}}


def body_hu(density: Image, calibration: HUCalibration, ct_hu: Image | None = None) -> Image:
    """CT numbers [HU] of a phase body known by its density [g/cm³] (a moved or virtual phase
    CT): ``ct_hu``'s own HU where the density is the one the calibration gives them (the
    reference CT unmoved), else the calibration's inverse, the lowest HU reaching the density
    (:meth:`HUCalibration.hu_of`; on a non-monotonic curve such as Schneider's around 100 HU the
    lower branch, soft tissue rather than marrow)."""
    rho = np.asarray(density.array, dtype=np.float64)
    hu = calibration.hu_of(rho)
    if ct_hu is not None:
        ct_hu.grid.require_same(density.grid, "the reference CT and the phase body")
        ref = np.asarray(ct_hu.array, dtype=np.float64)
        hu = np.where(calibration.density(ref) == rho, ref, hu)
    return Image(hu, density.grid)


def schneider_bodies(bodies_hu: list[Image], calibration: HUCalibration, hu_from: str
                     ) -> tuple[list[Image], dict[int, str], dict[str, Material],
                                dict[str, object]]:
    """Schneider labels of several bodies (the phases of a 4D run; no plan region claims their
    voxels): (label images, label → name, name → Material over all bodies, run record with the
    voxels of each bin per body and ``hu_from``, where the HU came from)."""
    labels, names, mats, voxels = [], {}, {}, []
    for hu in bodies_hu:
        lab, n, m = schneider_labels(hu, calibration, None, ())
        labels.append(lab)
        names.update(n)
        mats.update(m)
        voxels.append(assignment_record(lab, n)["voxels"])
    citation, _, _ = _table()
    return labels, names, mats, {"rule": "schneider", "citation": citation, "hu_from": hu_from,
                                 "voxels_per_phase": voxels}
