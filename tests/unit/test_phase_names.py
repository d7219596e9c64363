"""Per-phase files paired with the phases by the numbers in their names (issue 27)."""

from __future__ import annotations

from pathlib import Path

import pytest

from tetdose.core.phase_names import name_numbers, order_by_names, percents_from_names
from tetdose.errors import OptionError


def paths(*names: str) -> list[Path]:
    return [Path("/d") / n for n in names]


def test_numbers_from_percent_phase_words_and_one_template():
    assert name_numbers(paths("ct 20%.nrrd", "phase_040.0.nii.gz", "ph7.mha")) == [20, 40, 7]
    assert name_numbers(paths("dose0.3ddose", "dose12.3ddose")) == [0, 12]
    assert name_numbers(paths("6MV_a.csv", "6MV_b.csv")) == [None, None]  # not one template
    assert name_numbers(paths("a.csv", "b.csv")) == [None, None]


def test_order_by_indices_or_percentages_and_the_refusals():
    pct = [0.0, 33.3, 66.7]
    got = order_by_names(paths("phase_002.csv", "phase_000.csv", "phase_001.csv"), pct, "doses")
    assert [p.name for p in got] == ["phase_000.csv", "phase_001.csv", "phase_002.csv"]
    got = order_by_names(paths("p 66.7%.csv", "p 0%.csv", "p 33.3%.csv"), pct, "doses")
    assert [p.name for p in got] == ["p 0%.csv", "p 33.3%.csv", "p 66.7%.csv"]
    assert order_by_names(paths("c.csv", "a.csv", "b.csv"), pct, "doses") == paths(
        "c.csv", "a.csv", "b.csv")  # no numbers: the given order
    with pytest.raises(OptionError, match="doses: b.csv carries no phase number while"):
        order_by_names(paths("phase_000.csv", "b.csv", "phase_002.csv"), pct, "doses")
    with pytest.raises(OptionError, match="phase_001.csv and phase_001.csv both name phase 1"):
        order_by_names(paths("phase_000.csv", "phase_001.csv", "phase_001.csv"), pct, "doses")
    with pytest.raises(OptionError, match=r"neither the phases' percentages \(0, 33.3, 66.7 %\)"):
        order_by_names(paths("phase_000.csv", "phase_001.csv", "phase_005.csv"), pct, "doses")


def test_percents_from_names_of_files_that_define_the_phases():
    files, pct = percents_from_names(paths("phase_050.0.nrrd", "phase_000.0.nrrd"), "--dvf")
    assert [f.name for f in files] == ["phase_000.0.nrrd", "phase_050.0.nrrd"] and pct == [0, 50]
    files, pct = percents_from_names(paths("f1.nrrd", "f0.nrrd"), "--dvf")
    assert [f.name for f in files] == ["f0.nrrd", "f1.nrrd"] and pct is None  # indices
    files, pct = percents_from_names(paths("CT_3.nrrd", "CT_1.nrrd", "CT_2.nrrd"), "4D-CT")
    assert [f.name for f in files] == ["CT_1.nrrd", "CT_2.nrrd", "CT_3.nrrd"] and pct is None
    with pytest.raises(OptionError, match="names phase 120"):
        percents_from_names(paths("phase_120.nrrd", "phase_000.nrrd", "phase_3.nrrd"), "--dvf")
