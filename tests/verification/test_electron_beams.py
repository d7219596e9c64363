"""Broad electron beams in water: R50 and Rp of 6, 10 and 20 MeV against AAPM TG-25 (issue 19).

A broad parallel beam's central-axis depth dose in a laterally uniform phantom equals, by
reciprocity (translation invariance), the energy a pencil beam deposits per unit mass in a whole
infinite layer at that depth: D(z) = E_layer(z) / (ρ Δz) per unit fluence. So the phantom here is
one water column 800 × 800 mm² wide (wider than any lateral spread) in 1 mm deep voxels and the
source a pencil: every history scores, no lateral field edge to worry about.

Relations (mono-energetic beams, so the most probable and the mean surface energy are E0):

- mean energy: Ē0 = C4·R50, C4 = 2.33 MeV/cm (AAPM TG-25, Khan et al., Med. Phys. 18:73, 1991,
  eq. 2; ICRU Report 35, 1984) — R50 from the dose curve;
- practical range: E_p,0 = 0.22 + 1.98·Rp + 0.0025·Rp² [MeV, cm] (TG-25 eq. 1, after ICRU 35
  and Markus), Rp where the tangent through the steepest part of the fall-off meets the
  bremsstrahlung tail's level.

R50 and Rp are read between the 1 mm bins' centres by linear interpolation; the tangent is the
least-squares line through the bins between 20 % and 80 % of the maximum (the fall-off of a
mono-energetic beam is straight there); the tail level is the mean dose from Rp + 5 mm on;
D_max from a parabola through the peak (:func:`peak_dose`).

The reference of the same physics is EGSnrc, run side by side (ompmc, PEGS 700icru, so the
electron cut-off and δ-ray threshold Δ = 0.189 MeV are tetdose's): R50 and Rp within 1 mm, the
depth dose within 2 % of D_max + 3σ beyond 2 mm, and no dependence on the step size (ESTEPE 0.25
vs 0.05 within 0.5 mm); the same at ESTEPE 0.5 (the large steps of ``--max-energy-loss-fraction
0.5``) but for the 6 MeV beam's depth dose, a strict expected failure: +2.9 % of D_max at 2–4 mm,
−4.6 % at 13–16 mm (ESTEPE 0.25: +1.7 % / −1.6 %). TG-25's relations are fits to clinical
beams; EGSnrc itself misses them for these mono-energetic broad beams (measured: R50 24.3 / 42.0
/ 85.5 mm against 25.8 / 42.9 / 85.8, Rp 29.5 / 49.9 / 100.5 against 29.1 / 49.1 / 98.7), so
tetdose is held to TG-25 as closely as EGSnrc is (its miss + 0.5 mm, and at least 1 mm).
"""

from __future__ import annotations

import numpy as np
import pytest

from tetdose.core.image import Image, ImageGrid
from tetdose.transport import PhotonSource, Plan, TransportSettings, simulate

#: TG-25's C4 [MeV/cm].
C4_MEV_PER_CM = 2.33
#: Lateral size of the water column [mm] and depth-bin thickness [mm].
WIDTH_MM, BIN_MM = 800.0, 1.0
#: Electron cut-off and δ-ray threshold [MeV] kinetic: PEGS 700icru's AE = 0.700 MeV total.
CUTOFF_MEV = 0.189
#: Histories per curve.
HISTORIES = 100_000


def tg25_r50_mm(e0_mev: float) -> float:
    """R50 [mm] of TG-25's Ē0 = 2.33 MeV/cm · R50."""
    return e0_mev / C4_MEV_PER_CM * 10.0


def tg25_rp_mm(e0_mev: float) -> float:
    """Rp [mm] solving TG-25's E_p,0 = 0.22 + 1.98 Rp + 0.0025 Rp² (Rp in cm)."""
    a, b, c = 0.0025, 1.98, 0.22 - e0_mev
    return (-b + np.sqrt(b * b - 4 * a * c)) / (2 * a) * 10.0


def depth_dose(e0_mev: float, n: int, cutoff_mev: float = CUTOFF_MEV, seed: int = 1,
               engine: str = "tetdose", max_energy_loss_fraction: float = 0.25,
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(bin centres [mm], dose per history per bin [MeV/g ∝ Gy], σ) of a broad e⁻ beam computed
    by tetdose or by ompmc (``engine="ompmc"``: EGSnrc physics, PEGS 700icru, one thread)."""
    nz = int(np.ceil(e0_mev * 6.0 / BIN_MM)) + 20  # Rp ≈ 5 mm/MeV, then the tail
    grid = ImageGrid([0.0, 0.0, BIN_MM / 2], [WIDTH_MM, WIDTH_MM, BIN_MM], np.eye(3), (1, 1, nz))
    plan = Plan((PhotonSource("pencil", (0.0, 0.0, -5.0), (0, 0, 1), energies_mev=(e0_mev,),
                              particle="electron"),), materials={1: "water"})
    density = Image(np.ones(grid.shape), grid)
    labels = Image(np.ones(grid.shape, np.int32), grid)
    settings = TransportSettings(n, 10, seed, electron_cutoff_mev=cutoff_mev,
                                 max_energy_loss_fraction=max_energy_loss_fraction)
    if engine == "ompmc":
        from tetdose.coupling.ompmc import OmpmcOptions, simulate_ompmc

        res = simulate_ompmc(density, plan, settings, labels=labels, progress=False,
                             options=OmpmcOptions(pegs="700icru", electron_cutoff_mev=cutoff_mev,
                                                  threads=1))
    else:
        res = simulate(density, plan, settings, labels=labels, progress=False)
    e = res.energy_per_batch_mev.reshape(10, -1) / res.histories_per_batch[:, None]
    mass_g = res.mass_g.reshape(-1)
    d = e / mass_g
    return (np.arange(nz) + 0.5) * BIN_MM, d.mean(axis=0), d.std(axis=0, ddof=1) / np.sqrt(10)


def peak_dose(z: np.ndarray, d: np.ndarray) -> float:
    """D_max from a parabola through the bins within ±15 % of the depth of the highest bin (at
    least ±3 bins): the highest bin alone is biased upward by its noise."""
    i = int(np.argmax(d))
    half = max(3, int(round(0.15 * z[i] / (z[1] - z[0]))))
    sel = slice(max(i - half, 0), min(i + half + 1, len(d)))
    a, b, c = np.polyfit(z[sel], d[sel], 2)
    return float(c - b * b / (4 * a)) if a < 0 else float(d[i])


def r50_rp_mm(z: np.ndarray, d: np.ndarray) -> tuple[float, float]:
    """(R50, Rp) [mm] of a depth-dose curve (module docstring)."""
    i_max = int(np.argmax(d))
    rel = d / peak_dose(z, d)
    j = i_max + int(np.argmax(rel[i_max:] < 0.5))  # first bin below 50 % past the maximum
    r50 = z[j - 1] + (rel[j - 1] - 0.5) / (rel[j - 1] - rel[j]) * (z[j] - z[j - 1])
    fall = np.flatnonzero((rel > 0.2) & (rel < 0.8) & (np.arange(len(z)) > i_max))
    slope, icpt = np.polyfit(z[fall], rel[fall], 1)
    rp = (0.0 - icpt) / slope
    tail = rel[z > rp + 5.0].mean()
    return float(r50), float((tail - icpt) / slope)




def test_tg25_relations_are_as_published():
    """The relations themselves (TG-25 Table I region: 10 MeV ↔ R50 4.29 cm, Rp ≈ 4.93 cm)."""
    assert tg25_r50_mm(10.0) == pytest.approx(42.9, abs=0.05)
    assert 0.22 + 1.98 * tg25_rp_mm(10.0) / 10 + 0.0025 * (tg25_rp_mm(10.0) / 10) ** 2 == \
        pytest.approx(10.0)


def test_r50_and_rp_of_a_synthetic_curve():
    """The reader finds R50 and Rp of a curve with a straight fall-off and a flat tail."""
    z = np.arange(60) + 0.5
    d = np.clip(1.0 - (z - 30.0) / 10.0 * 0.8, 0.03, 1.0)  # 100 % to 30 mm, −8 %/mm, tail 3 %
    r50, rp = r50_rp_mm(z, d)
    assert r50 == pytest.approx(30.0 + 0.5 / 0.08, abs=1e-9)
    assert rp == pytest.approx(30.0 + 0.97 / 0.08, abs=1e-9)


#: Measured (10⁵ histories each, Δ = 0.189 MeV, ESTEPE 0.25): tetdose R50 24.23 / 41.72 / 84.97 mm,
#: Rp 29.42 / 49.93 / 99.74 mm; EGSnrc (ompmc) R50 24.29 / 41.99 / 85.46, Rp 29.54 / 49.89 / 100.47.
#: Before the multiple-scattering law had the right second moment (first moment only), Rp was
#: 1.2–2 mm deeper than EGSnrc's and moved 1.3 mm between ESTEPE 0.25 and 0.01.
ENERGIES_MEV = (6.0, 10.0, 20.0)
#: ESTEPE 0.5 at 6 MeV misses the depth-dose criterion (measured: +2.9 % of D_max at 2–4 mm,
#: −4.6 % at 13–16 mm; ESTEPE 0.25 there: +1.7 % / −1.6 %); at 10 and 20 MeV it meets it.
_COARSE_6MEV = pytest.mark.xfail(strict=True, reason="ESTEPE 0.5 is too coarse for a 6 MeV "
                                 "electron beam's depth dose (measured up to 4.6 % of D_max)")


@pytest.fixture(scope="module")
def curves() -> dict[tuple[str, float], tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Depth-dose curves by (engine, energy): tetdose, tetdose at ESTEPE 0.05 and 0.5, ompmc."""
    pytest.importorskip("ompmc", reason="ompmc (tetdose[ompmc]) is the EGSnrc reference")
    out = {}
    for e0 in ENERGIES_MEV:
        out["tetdose", e0] = depth_dose(e0, HISTORIES)
        out["estepe 0.05", e0] = depth_dose(e0, HISTORIES, max_energy_loss_fraction=0.05)
        out["estepe 0.5", e0] = depth_dose(e0, HISTORIES, max_energy_loss_fraction=0.5)
        out["ompmc", e0] = depth_dose(e0, HISTORIES, engine="ompmc")
    return out


def ranges_mm(curves, kind: str, e0_mev: float) -> np.ndarray:  # noqa: ANN001
    """(R50, Rp) [mm] of one curve of the :func:`curves` fixture."""
    return np.array(r50_rp_mm(*curves[kind, e0_mev][:2]))


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["tetdose", "estepe 0.5"])
@pytest.mark.parametrize("e0_mev", ENERGIES_MEV)
def test_broad_electron_beam_r50_and_rp_match_egsnrc(curves, e0_mev, kind):
    ours, egs = ranges_mm(curves, kind, e0_mev), ranges_mm(curves, "ompmc", e0_mev)
    assert np.all(np.abs(ours - egs) <= 1.0), (ours, egs)


@pytest.mark.slow
@pytest.mark.parametrize(("e0_mev", "kind"), [
    *((e0, "tetdose") for e0 in ENERGIES_MEV),
    pytest.param(6.0, "estepe 0.5", marks=_COARSE_6MEV), (10.0, "estepe 0.5"),
    (20.0, "estepe 0.5")])
def test_broad_electron_beam_depth_dose_matches_egsnrc(curves, e0_mev, kind):
    z, d, sd = curves[kind, e0_mev]
    _, d_ref, sd_ref = curves["ompmc", e0_mev]
    beyond = z > 2.0
    allowed = 0.02 * peak_dose(z, d_ref) + 3.0 * np.hypot(sd, sd_ref)
    miss = 100.0 * (d - d_ref) / peak_dose(z, d_ref)  # [% of D_max], in the message
    assert np.all(np.abs(d - d_ref)[beyond] <= allowed[beyond]), \
        f"{kind} {e0_mev} MeV: {miss[beyond].max():+.1f} % at {z[beyond][miss[beyond].argmax()]:.1f} " \
        f"mm, {miss[beyond].min():+.1f} % at {z[beyond][miss[beyond].argmin()]:.1f} mm of D_max"


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["tetdose", "estepe 0.5"])
@pytest.mark.parametrize("e0_mev", ENERGIES_MEV)
def test_broad_electron_beam_does_not_depend_on_the_step_size(curves, e0_mev, kind):
    shift = ranges_mm(curves, kind, e0_mev) - ranges_mm(curves, "estepe 0.05", e0_mev)
    assert np.all(np.abs(shift) <= 0.5), shift


@pytest.mark.slow
@pytest.mark.parametrize("e0_mev", ENERGIES_MEV)
def test_broad_electron_beam_is_as_close_to_tg25_as_egsnrc(curves, e0_mev):
    tg25 = np.array([tg25_r50_mm(e0_mev), tg25_rp_mm(e0_mev)])
    miss, egs_miss = (np.abs(ranges_mm(curves, k, e0_mev) - tg25) for k in ("tetdose", "ompmc"))
    assert np.all(miss <= np.maximum(egs_miss + 0.5, 1.0)), (miss, egs_miss)
