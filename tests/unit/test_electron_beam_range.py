"""Fast variant of the broad electron-beam verification (tests/verification/test_electron_beams.py):
a 6 MeV beam in water, few histories: R50 against EGSnrc (ompmc) run side by side within 1 mm,
and against TG-25's Ē0 = 2.33 MeV/cm · R50 within 2 mm (EGSnrc itself is 1.5 mm short)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "verification"))
from test_electron_beams import depth_dose, r50_rp_mm, tg25_r50_mm  # noqa: E402


def test_6mev_broad_beam_r50_matches_tg25():
    z, d, sd = depth_dose(6.0, 3000, seed=5)
    r50, rp = r50_rp_mm(z, d)
    assert r50 == pytest.approx(tg25_r50_mm(6.0), abs=2.0)
    assert r50 < rp < 40.0
    assert d[:3].mean() < d.max()  # the dose builds up under the surface


def test_6mev_broad_beam_r50_matches_egsnrc():
    pytest.importorskip("ompmc", reason="ompmc (tetdose[ompmc]) is the EGSnrc reference")
    ours = r50_rp_mm(*depth_dose(6.0, 3000, seed=5)[:2])
    egs = r50_rp_mm(*depth_dose(6.0, 3000, seed=5, engine="ompmc")[:2])
    assert ours[0] == pytest.approx(egs[0], abs=1.0), (ours, egs)
