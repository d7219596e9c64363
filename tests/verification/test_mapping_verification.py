"""The density-mapping paper's preliminary experiment (§IV.C.1, Figs. 11–12) on the ``cube`` phantom.

An n×n×n crop of normally distributed HU (n = 3…10) covered exactly by the same 20-tetrahedron,
18-vertex mesh. The paper reports a mass error below 1 % and a relative mean density error
(RMDE, eq. 24–25) that rises with n (fewer vertices per voxel) and with the image's standard
deviation (more heterogeneity). One image is a noisy sample, so the trends are asserted on the
mean RMDE over ``N_SEEDS`` seeded images per point (the paper's figures also pool several crops).
``bench/bench_paper_cube.py`` prints the full table and draws the figures.
"""

from __future__ import annotations

import numpy as np
import pytest

from tetdose.mapping import map_density
from tetdose.mapping.metrics import evaluate
from tetdose.phantoms import make_phantom

N_SEEDS = 10
SIZES = (3, 5, 7, 10)
STDS_HU = (10.0, 50.0, 100.0, 200.0)


def cube_metrics(n: int, std_hu: float, seed: int, solver: str) -> tuple[float, float, float]:
    """(RMDE %, eq. 23 mass error %, solver's own relative mass error) for one cube image."""
    ph = make_phantom("cube", seed=seed, n=n, std_hu=std_hu)
    dm = map_density(ph.mesh, ph.ct, solver=solver)
    m = evaluate(ph.ct, dm.mesh, dm.density_g_cm3, overlap=dm.overlap).metrics
    assert m.n_voxels == n**3  # the mesh covers every voxel exactly
    return m.rmde_pct, m.mass_error_pct, dm.mass_error_covered


def mean_rmde(n: int, std_hu: float, solver: str) -> float:
    return float(np.mean([cube_metrics(n, std_hu, s, solver)[0] for s in range(N_SEEDS)]))


@pytest.mark.parametrize("solver", ["l2", "lsq"])
def test_rmde_rises_with_image_size(solver: str) -> None:
    """Fig. 11: same 18 vertices, more voxels → larger mean local density error."""
    rmde = [mean_rmde(n, 50.0, solver) for n in SIZES]
    assert np.all(np.diff(rmde) > 0), rmde


@pytest.mark.parametrize("solver", ["l2", "lsq"])
def test_rmde_rises_with_image_standard_deviation(solver: str) -> None:
    """Fig. 12: more heterogeneous image → larger error; for small noise about ∝ σ."""
    rmde = [mean_rmde(5, s, solver) for s in STDS_HU]
    assert np.all(np.diff(rmde) > 0), rmde
    # With the same noise pattern scaled, the error grows about linearly in σ (density ≈ 1.05):
    # doubling σ from 50 to 100 HU roughly doubles it.
    assert 1.6 < rmde[2] / rmde[1] < 2.4


def test_mass_is_kept_on_every_cube() -> None:
    """Paper: mass error < 1 %; the mass-conserving solve keeps it to round-off."""
    for n in SIZES:
        for seed in range(3):
            _, mass_error_pct, own = cube_metrics(n, 200.0, seed, "l2")
            assert mass_error_pct < 1e-7
            assert own < 1e-9
            _, mass_error_pct, _ = cube_metrics(n, 200.0, seed, "lsq")
            assert mass_error_pct < 1.0
