"""Dose to water of a run's cells (``dose_to="water"``): D_w = D_m · s_w,m per cell.

A dose-mode run tallies, per cell, the Spencer–Attix sums A = Σ wt·s·L_w(Ē) and
B = Σ wt·s·L_m(Ē) over the electron steps that crossed it, plus the track-end terms
(:mod:`tetdose.transport.history._electron`; Siebers, Keall, Nahum & Mohan, PMB 45:983, 2000),
so s_w,m = A/B is the ratio averaged over the fluence that cell actually tracked; it converts
all of the cell's energy (also that of electrons born below the cut-off and photons below
theirs, which add to neither sum). Cells no electron crossed (B = 0) and the ompMC engine (no
tracked fluence) take the per-medium ratio of :mod:`tetdose.transport.physics.dose_to_water`
(the documented fallback).
"""

from __future__ import annotations

import numpy as np

from tetdose._typing import BoolArray, FloatArray, IntArray
from tetdose.transport.physics.dose_to_water import (
    DEFAULT_QUALITY,
    METHOD,
    TRACKED_METHOD,
    water_to_medium_ratio,
)
from tetdose.transport.physics.materials import Material, resolve_material
from tetdose.transport.run.settings import TransportSettings


def water_factors(names: list[str | Material], settings: TransportSettings
                  ) -> tuple[FloatArray, dict[str, object]]:
    """Per material: the factor from the tallied energy to the reported one (the per-medium
    s_w,m for dose to water, else 1), and the record of the conversion."""
    if settings.dose_to != "water":
        return np.ones(len(names)), {}
    ratios = {resolve_material(m).name: water_to_medium_ratio(m) for m in names}
    return np.array(list(ratios.values())), {"dose_to_water": {
        "method": METHOD.format(quality=DEFAULT_QUALITY), "s_w_m": ratios}}


def tracked_water_factors(names: list[str | Material], material_of_cell: IntArray,
                          settings: TransportSettings, sums: FloatArray, dosed: BoolArray
                          ) -> tuple[FloatArray, dict[str, object]]:
    """Per cell: s_w,m = A/B from the sums ``sums`` (2, n_cells) [MeV] (module docstring);
    cells with B = 0 take their medium's (``material_of_cell``, index into ``names``)
    per-medium ratio. The record says so, how many cells with dose (``dosed``) fell back, and
    per medium Σ A / Σ B over its cells (the fluence-averaged s_w,m; the per-medium ratio where
    no electron crossed it)."""
    table, fallback = water_factors(names, settings)
    a, b = sums
    crossed = b > 0.0
    factor = table[material_of_cell]
    factor[crossed] = a[crossed] / b[crossed]
    mean = {}
    for i, m in enumerate(names):
        cells = material_of_cell == i
        bm = b[cells].sum()
        mean[resolve_material(m).name] = float(a[cells].sum() / bm) if bm > 0.0 else float(table[i])
    return factor, {"dose_to_water": {
        "method": TRACKED_METHOD, "s_w_m": mean, "cells_fallback": int((dosed & ~crossed).sum()),
        "cells_dosed": int(dosed.sum()), "fallback": fallback["dose_to_water"]}}


def convert(names: list[str | Material], material_of_cell: IntArray | None,
            settings: TransportSettings, energy: FloatArray, sums: FloatArray
            ) -> tuple[FloatArray | None, dict[str, object]]:
    """Multiply the batch rows ``energy`` (B, n_cells) in place by each cell's s_w,m: from the
    tracked ``sums`` when there are any (n_cells columns), else per medium (dose to water
    only). Returns (the per-cell factor of the tracked conversion or None, the record)."""
    if sums.shape[1] > 0:
        ratio, record = tracked_water_factors(names, material_of_cell, settings, sums,
                                              energy.any(axis=0))
        energy *= ratio[None, :]  # D_w = D_m · s_w,m, same mass
        return ratio, record
    factor, record = water_factors(names, settings)
    if material_of_cell is not None and record:
        energy *= factor[material_of_cell][None, :]
    return None, record
