"""tetdose's coupled transport against ompmc (EGSnrc physics) run in the same test (issue 19).

Both codes get the same voxels (lateral 10 mm, 1 mm deep), the same source particles (tetdose's
sampler; ompmc replays them), the same 10 keV electron and photon cut-offs (ompmc's 521icru file:
AE = 0.521 MeV total) and the same materials (water → H2O521ICRU, lung 0.26 g/cm³ → LUNG521ICRU,
ICRU lung at its nominal density). Central-axis column: the 10 mm voxel column on the axis (30 mm
field) or 30 × 30 mm² (100 mm field). Criteria of issue 19, each allowed 3 σ of the difference
of the two runs' statistical noise on top (the test budget: a few minutes; the production
comparison with 10⁶–10⁷ histories is ``bench/validate_vs_ompmc.py``):

- build-up, 1 mm bins from the surface to 6 mm: |ΔD| ≤ 3 % of D_max;
- beyond, 5 mm bins (2 % of the local dose; 1 mm is 0.5 % of the dose at these gradients);
- lung (35–95 mm, 5 mm from the interfaces): the mean dose within 1 %.
"""

from __future__ import annotations

import numpy as np
import pytest

from tetdose.core.image import Image, ImageGrid
from tetdose.plan.spectra import named_spectrum
from tetdose.transport import PhotonSource, Plan, TransportSettings, simulate

pytest.importorskip("ompmc", reason="ompmc (tetdose[ompmc]) is not installed")
from tetdose.coupling.ompmc import OmpmcOptions, simulate_ompmc  # noqa: E402

LATERAL_MM, N_LATERAL, DEPTH_MM = 10.0, 15, 130
LUNG_MM = (30, 100)
CUTOFF_MEV = 0.01


def _phantom(slab: bool) -> tuple[Image, Image]:
    half = N_LATERAL * LATERAL_MM / 2
    grid = ImageGrid([-half + LATERAL_MM / 2, -half + LATERAL_MM / 2, 0.5],
                     [LATERAL_MM, LATERAL_MM, 1.0], np.eye(3), (N_LATERAL, N_LATERAL, DEPTH_MM))
    depth = np.arange(DEPTH_MM) + 0.5
    lung = (depth > LUNG_MM[0]) & (depth < LUNG_MM[1]) if slab else np.zeros(DEPTH_MM, bool)
    rho = np.where(lung, 0.26, 1.0)[:, None, None] * np.ones(grid.shape)
    lab = (np.where(lung, 2, 1)[:, None, None] * np.ones(grid.shape)).astype(np.int32)
    return Image(rho, grid), Image(lab, grid)


def _plan(beam: str, field_mm: float) -> Plan:
    e, w = (np.array([2.0]), np.ones(1)) if beam == "2MeV" else named_spectrum(beam)
    src = PhotonSource("parallel", [0.0, 0.0, -50.0], [0, 0, 1], energies_mev=e, line_weights=w,
                       field_mm=[field_mm, field_mm])
    return Plan((src,), materials={1: "water", 2: "lung"})


def _column(result, grid: ImageGrid, field_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """(per-batch energy per history by depth voxel (B, nz) [MeV], column mass by depth [g])."""
    c = N_LATERAL // 2
    cols = slice(c, c + 1) if field_mm < 50 else slice(c - 1, c + 2)
    e = result.energy_per_batch_mev.reshape(-1, *grid.shape)[:, :, cols, cols].sum(axis=(2, 3))
    return e / result.histories_per_batch[:, None], \
        result.mass_g.reshape(grid.shape)[:, cols, cols].sum(axis=(1, 2))


def _bin(e: np.ndarray, m: np.ndarray, lo: int, hi: int) -> tuple[float, float]:
    per_batch = e[:, lo:hi].sum(axis=1) / m[lo:hi].sum()
    return float(per_batch.mean()), float(per_batch.std(ddof=1) / np.sqrt(len(per_batch)))


def _compare(beam: str, field_mm: float, slab: bool, n_tetdose: int, n_ompmc: int,
             **tetdose_settings: object) -> list[str]:
    rho, lab = _phantom(slab)
    plan = _plan(beam, field_mm)
    t = simulate(rho, plan, TransportSettings(n_tetdose, 10, 11, energy_cutoff_mev=CUTOFF_MEV,
                                              electron_cutoff_mev=CUTOFF_MEV,
                                              **tetdose_settings),
                 labels=lab, progress=False)
    o = simulate_ompmc(rho, plan, TransportSettings(n_ompmc, 10, 12, energy_cutoff_mev=CUTOFF_MEV),
                       labels=lab, progress=False,
                       options=OmpmcOptions(electron_cutoff_mev=CUTOFF_MEV))
    assert o.extra["media"]["water"]["pegs"] == "H2O521ICRU"
    if slab:
        assert o.extra["media"]["lung"]["pegs"] == "LUNG521ICRU"
    (et, m), (eo, _) = _column(t, rho.grid, field_mm), _column(o, rho.grid, field_mm)
    build = [(z, z + 1) for z in range(6)]
    deep = [(z, z + 5) for z in range(10, DEPTH_MM - 5, 5)
            if not (slab and LUNG_MM[0] - 3 < z + 2.5 < LUNG_MM[1] + 3)]
    d_max = max(_bin(eo, m, z, z + 2)[0] for z in range(6, 30, 2))
    bad = []
    for lo, hi in build + deep:
        dt, st = _bin(et, m, lo, hi)
        do, so = _bin(eo, m, lo, hi)
        tol = 0.03 * d_max if hi <= 6 else 0.02 * do
        if abs(dt - do) > tol + 3 * np.hypot(st, so):
            bad.append(f"{lo}-{hi} mm: tetdose {dt:.4g} ± {st:.2g}, ompmc {do:.4g} ± {so:.2g}")
    if slab:
        lo, hi = LUNG_MM[0] + 5, LUNG_MM[1] - 5
        (dt, st), (do, so) = _bin(et, m, lo, hi), _bin(eo, m, lo, hi)
        if abs(dt / do - 1) > 0.01 + 3 * np.hypot(st, so) / do:
            bad.append(f"lung: tetdose {dt:.4g} ± {st:.2g}, ompmc {do:.4g} ± {so:.2g}")
    return bad


@pytest.mark.slow
def test_2mev_water_lung_water_slab_30mm_field_matches_ompmc():
    assert _compare("2MeV", 30.0, True, 1_000_000, 40_000) == []


#: The recommended fast setting (docs/theory.md): XVMC's splitting along the ray, the source
#: photon in 64 copies and later photons in 32, tracks replayed across media, quasi-random
#: source photons.
FAST = {"photon_splitting": 64, "secondary_photon_splitting": 32, "splitting_scheme": "repeat",
        "quasi_random": True}


@pytest.mark.slow
def test_2mev_slab_matches_ompmc_with_splitting_along_the_ray_and_large_steps():
    """The fast setting with ESTEPE 0.5, on the same slab, against the same EGSnrc run."""
    assert _compare("2MeV", 30.0, True, 150_000, 40_000, max_energy_loss_fraction=0.5,
                    **FAST) == []


@pytest.mark.slow
def test_6mv_water_100mm_field_matches_ompmc_with_the_fast_setting():
    """The fast setting at the default step size, 6 MV in water, against EGSnrc."""
    assert _compare("6MV", 100.0, False, 150_000, 40_000, **FAST) == []


@pytest.mark.slow
def test_6mv_water_100mm_field_matches_ompmc():
    assert _compare("6MV", 100.0, False, 1_000_000, 40_000) == []
