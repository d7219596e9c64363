"""Mesh and voxel engines agree on a water/lung/bone slab phantom within statistics.

The mesh conforms to the voxel grid (each voxel = 6 Kuhn tets, ``helpers.box_mesh`` numbers the
tets voxel by voxel in flat voxel order), so both engines see identical geometry, densities and
materials, and resampling the mesh dose by volume overlap is exact: voxel energy = Σ energy of
its 6 tets, voxel mass = Σ tet masses. Independent seeds make the two runs independent, so per
voxel z = (D_mesh − D_voxel)/√(σ_m² + σ_v²) is ~ N(0, 1) (t-like with batch σ): we check
max |z|, the mean of z (no bias) and the mean of z² (σ neither under- nor over-stated).
Vertices are split per region so the density jumps at the slab faces.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from tetdose.core.image import Image
from tetdose.transport import PhotonSource, Plan, TransportSettings, simulate

from helpers import box_mesh, grid_for

#: (z_start_mm, region, material, density g/cm³): water, lung, bone, water.
SLABS = ((0.0, 1, "water", 1.0), (20.0, 2, "lung", 0.26), (50.0, 3, "cortical_bone", 1.85),
         (60.0, 1, "water", 1.0))


def slab_phantom(n_xy: int, n_z: int, depth_mm: float = 100.0, width_mm: float = 60.0):
    """(mesh with split vertices and point density, density image, label image, plan)."""
    lo, hi = (-width_mm / 2, -width_mm / 2, 0.0), (width_mm / 2, width_mm / 2, depth_mm)
    mesh = box_mesh(lo, hi, (n_xy, n_xy, n_z))
    grid = grid_for(lo, hi, (width_mm / n_xy, width_mm / n_xy, depth_mm / n_z))
    starts = np.array([s[0] for s in SLABS])
    slab_of = lambda z: np.searchsorted(starts, z, side="right") - 1  # noqa: E731
    tet_slab = slab_of(mesh.centroids_mm[:, 2])
    voxel_slab = slab_of(grid.voxel_centers_mm()[:, 2])
    region = np.array([s[1] for s in SLABS])
    rho = np.array([s[3] for s in SLABS])
    split = type(mesh)(mesh.points_mm, mesh.tets, region[tet_slab]).split_by_region()
    point_rho = np.empty(split.n_points)
    point_rho[split.tets] = rho[tet_slab][:, None]
    mesh = split.with_data(point_data={"density": point_rho})
    density = Image(rho[voxel_slab].reshape(grid.shape), grid)
    labels = Image(region[voxel_slab].reshape(grid.shape).astype(np.int16), grid)
    plan = Plan((PhotonSource("parallel", [0.0, 0.0, -20.0], [0, 0, 1], energies_mev=[1.25],
                              field_mm=[width_mm / 3, width_mm / 3]),),
                materials={s[1]: s[2] for s in SLABS})
    return mesh, density, labels, plan


def _voxel_dose(energy_rows, hist_rows, mass_g):
    """(mean, σ of the mean) per cell from batch rows, MeV/g per source particle."""
    x = energy_rows / hist_rows[:, None]
    return x.mean(0) / mass_g, x.std(0, ddof=1) / math.sqrt(len(x)) / mass_g


def compare_engines(n_xy, n_z, n_hist, n_batches):
    mesh, density, labels, plan = slab_phantom(n_xy, n_z)
    rm = simulate(mesh, plan, TransportSettings(n_hist, n_batches, 101, physics="kerma"), progress=False)
    rv = simulate(density, plan, TransportSettings(n_hist, n_batches, 202, physics="kerma"), labels=labels,
                  progress=False)
    assert rm.lost_photons == 0 and rv.lost_photons == 0
    assert sorted(rm.extra["materials"]) == sorted(rv.extra["materials"]) == sorted(
        ["water", "lung", "cortical_bone"])
    # volume-overlap resampling of a conforming mesh: 6 consecutive tets per voxel
    mass_m = rm.mass_g.reshape(-1, 6).sum(1)
    np.testing.assert_allclose(mass_m, rv.mass_g, rtol=1e-12)
    dm, sm = _voxel_dose(rm.energy_per_batch_mev.reshape(n_batches, -1, 6).sum(2),
                         rm.histories_per_batch, mass_m)
    dv, sv = _voxel_dose(rv.energy_per_batch_mev, rv.histories_per_batch, rv.mass_g)
    s = np.sqrt(sm**2 + sv**2)
    ok = (dm > 0) & (sm < 0.2 * dm) & (sv < 0.2 * dv)
    z = (dm[ok] - dv[ok]) / s[ok]
    return z, ok, density


def _check(z, rho):
    """No outlier, no bias overall nor per tissue (a bias local to one slab shows there)."""
    n = len(z)
    assert np.max(np.abs(z)) < 5.0
    assert abs(z.mean()) < 4.0 / math.sqrt(n)
    assert 0.6 < np.mean(z**2) < 1.0 + 6.0 / math.sqrt(n)
    for tissue_rho in {s[3] for s in SLABS}:
        zt = z[rho == tissue_rho]
        assert len(zt) >= 20  # every tissue is compared, not only water
        assert abs(zt.mean()) < 4.0 / math.sqrt(len(zt)), f"bias in ρ = {tissue_rho} g/cm³"


def test_mesh_and_voxel_agree_on_lung_bone_slabs():
    z, ok, density = compare_engines(6, 10, 20_000, 20)
    _check(z, density.array.reshape(-1)[ok])


@pytest.mark.slow
def test_mesh_and_voxel_agree_on_lung_bone_slabs_production_size():
    """4 M histories per engine on 5 mm voxels. Bone treated as water in the mesh run only
    (μen/ρ 6 % off) fails here with max |z| ≈ 34, and fails the fast test with max |z| ≈ 6."""
    z, ok, density = compare_engines(12, 20, 4_000_000, 20)
    assert len(z) > 1000
    _check(z, density.array.reshape(-1)[ok])
