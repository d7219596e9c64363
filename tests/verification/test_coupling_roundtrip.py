"""Issue 21's round trip with the real engine, offline: each phase's virtual CT through ompmc
(EGSnrc physics), its dose written as an EGSnrc .3ddose, imported onto the mesh and accumulated.

The import reads only the file (dose and relative uncertainty, 17 digits); the reference puts the
run's own per-batch voxel energies on the tets (:func:`tetdose.coupling.onto_mesh.result_onto_mesh`,
another route through the same overlaps). The accumulation must equal the per-phase energy sum over
the mesh mass, D_k = Σ_p w_p D_kp m_kp / Σ_p w_p m_kp, to 1e-9.
"""

from __future__ import annotations

import numpy as np
import pytest

from tetdose.core.image import Image
from tetdose.core.mass import tet_mass_g
from tetdose.core.voxelize import voxelize
from tetdose.coupling.import_dose import import_doses
from tetdose.coupling.onto_mesh import result_onto_mesh
from tetdose.coupling.threeddose import write_3ddose
from tetdose.motion.phases import PhaseSeries
from tetdose.plan.model import Plan
from tetdose.plan.photon_source import PhotonSource
from tetdose.transport.run.settings import TransportSettings

from helpers import box_mesh, grid_for

ompmc = pytest.importorskip("ompmc")


@pytest.mark.slow
def test_ompmc_phases_through_3ddose_accumulate_on_the_mesh(tmp_path):
    from tetdose.coupling.ompmc import simulate_ompmc

    mesh = box_mesh([-10, -10, -8], [10, 10, 8], (4, 4, 3), jitter=0.2, seed=1)
    rho = 0.9 + 0.01 * mesh.points_mm[:, 0]
    shifts = np.array([[0.0, 0.0, 0.0], [0.0, 1.0, 3.0]])
    series = PhaseSeries(mesh, mesh.points_mm[None] + shifts[:, None, :], time_weight=[0.6, 0.4],
                         density_g_cm3=np.stack([rho, rho]))
    grid = grid_for([-20, -20, -20], [20, 20, 20], [2.0, 2.0, 2.0])
    water = Image(np.full(grid.shape, 1.0), grid)
    plan = Plan((PhotonSource("parallel", [0.0, 0.0, -30.0], [0, 0, 1], energies_mev=[1.25],
                              field_mm=[24.0, 24.0]),))
    settings = TransportSettings(n_histories=20_000, n_batches=4, seed=3)
    files, densities, reference = [], [], []
    for k in range(2):
        phase = series.mesh(k)
        rho_v = voxelize(phase, series.density_g_cm3[k], grid, background=water)
        result = simulate_ompmc(rho_v, plan, settings, progress=False)
        dose, std = result.to_images()
        rel = np.divide(std.array, dose.array, out=np.zeros(grid.shape), where=dose.array > 0)
        files.append(write_3ddose(tmp_path / f"phase_{k}.3ddose", dose, dose.with_array(rel)))
        densities.append(rho_v)
        reference.append(result_onto_mesh(result, rho_v, phase).dose_gy)
    imported = import_doses(series, files, densities=densities)
    for k in range(2):
        assert reference[k].max() > 0
        np.testing.assert_allclose(imported.phases[k].dose_gy, reference[k], rtol=1e-9,
                                   atol=1e-12 * reference[k].max())
    w = series.time_weight
    m = np.stack([tet_mass_g(series.mesh(k)) for k in range(2)])
    want = (w[:, None] * np.stack(reference) * m).sum(0) / (w[:, None] * m).sum(0)
    np.testing.assert_allclose(imported.accumulated.dose_gy, want, rtol=1e-9,
                               atol=1e-12 * want.max())
