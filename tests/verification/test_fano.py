"""Fano test of the condensed-history electron transport (issue 19): in a medium of one composition
with any density pattern, particles born uniformly per unit mass give a dose that is uniform and
equal to the emitted energy per unit mass wherever the outer surface is out of reach (Fano 1954;
the benchmark of EGSnrc's boundary crossing, Kawrakow, Med. Phys. 27:499, 2000).

Phantoms (water throughout, through one region material): a box whose density rises linearly
from 0.5 to 2 g/cm³ along x (jittered tets with the linear vertex density, and the voxel twin
with each voxel's mean density), and a box of three slabs 1.0 | 0.26 | 1.85 g/cm³ (tets split by
region, so the density jumps across the interfaces; and the voxel twin). Source: a volume source
of mono-energetic electrons filling the world. Photons are not transported (photon cut-off
19.9 MeV: every bremsstrahlung loss is continuous and local), which the theorem needs in a
finite phantom. "Interior" cells lie farther than 1.1 × the CSDA range from the outer surface in
mass thickness along every straight line (x: the column density to each x face; y, z: the
distance times the smallest density).

The ratio reported is (Σ_interior E / Σ_interior m) / (E₀ / M_world); its standard deviation
comes from the batches. Fast versions check it at a few per cent; the production sizes
(``slow``) at 0.5 %, for 0.1, 1 and 5 MeV and three step sizes (ESTEPE 0.5, 0.25, 0.05).
"""

from __future__ import annotations

import numpy as np
import pytest

from tetdose.core.image import Image, ImageGrid
from tetdose.core.mesh import TetMesh
from tetdose.plan.model import Plan
from tetdose.plan.volume_source import VolumeSource
from tetdose.transport import simulate
from tetdose.transport.geometry.world import World
from tetdose.transport.physics.electron_xs import csda_range_g_cm2
from tetdose.transport.run.settings import TransportSettings

import helpers

#: Photon cut-off that keeps every photon local (no bremsstrahlung photon is produced).
NO_PHOTONS_MEV = 19.9
#: Reference phantom size at 1 MeV [mm] (scaled by the CSDA range for other energies).
SIZE_1MEV_MM = 100.0
STEP_DENSITIES = (1.0, 0.26, 1.85)


def _range_g_cm2(e_mev: float) -> float:
    return 1.1 * float(csda_range_g_cm2("water", np.array([e_mev]))[0])


def _column_g_cm2(profile, x_mm: np.ndarray, length_mm: float) -> np.ndarray:
    """∫_0^x ρ(x') dx' [g/cm²] of a density profile along x, by fine trapezoids."""
    xs = np.linspace(0.0, length_mm, 20001)
    cum = np.concatenate([[0.0], np.cumsum(0.5 * (profile(xs[1:]) + profile(xs[:-1]))
                                           * np.diff(xs))]) / 10.0
    return np.interp(x_mm, xs, cum)


def _interior(lo, hi, profile, size, r_g_cm2, rho_min):
    """Cells (bounding boxes lo, hi (n, 3) [mm]) beyond the surface's reach (module doc)."""
    lx = size[0]
    margin_yz = r_g_cm2 / rho_min * 10.0
    inside = np.all((lo[:, 1:] > margin_yz) & (hi[:, 1:] < size[1:] - margin_yz), axis=1)
    left = _column_g_cm2(profile, lo[:, 0], lx)
    right = _column_g_cm2(profile, np.full(1, lx), lx) - _column_g_cm2(profile, hi[:, 0], lx)
    return inside & (left > r_g_cm2) & (right > r_g_cm2)


def _linear_profile(lx):
    return lambda x: 0.5 + 1.5 * np.asarray(x) / lx


def _step_profile(lx):
    edges = np.array([lx / 3, 2 * lx / 3])
    return lambda x: np.asarray(STEP_DENSITIES)[np.searchsorted(edges, np.asarray(x), "right")]


def _phantom(kind: str, e_mev: float, n: int):
    """(world, interior mask (cells in result order), profile) of one Fano phantom."""
    r = _range_g_cm2(e_mev)
    scale = r / _range_g_cm2(1.0)
    steps = kind.endswith("steps")
    lx = SIZE_1MEV_MM * scale
    lyz = 1.5 * lx if steps else lx  # room for the reach in the 0.26 g/cm³ slab
    size = np.array([lx, lyz, lyz])
    profile = _step_profile(lx) if steps else _linear_profile(lx)
    rho_min = min(STEP_DENSITIES) if steps else 0.5
    if kind.startswith("mesh"):
        mesh = helpers.box_mesh((0, 0, 0), size, (n, n, n),
                                jitter=0.0 if steps else 0.2, seed=1)
        cx = mesh.centroids_mm[:, 0]
        region = np.searchsorted([lx / 3, 2 * lx / 3], cx) + 1 if steps else np.ones(
            mesh.n_tets, int)
        mesh = TetMesh(mesh.points_mm, mesh.tets, region)
        if steps:
            mesh = mesh.split_by_region()  # each region its own vertex copies
            rho_p = np.empty(mesh.n_points)
            rho_p[mesh.tets.ravel()] = np.asarray(STEP_DENSITIES)[np.repeat(mesh.region, 4) - 1]
        else:
            rho_p = profile(mesh.points_mm[:, 0])
        mesh = mesh.with_data(point_data={"density": rho_p})
        pts = mesh.points_mm[mesh.tets]
        interior = _interior(pts.min(axis=1), pts.max(axis=1), profile, size, r, rho_min)
        return World(mesh=mesh), interior, r
    shape = (n, n, n)
    spacing = size / np.array(shape)
    grid = ImageGrid(spacing / 2, spacing, np.eye(3), shape)
    ijk = np.indices(grid.shape).reshape(3, -1).T[:, ::-1]  # (i, j, k) in flat (z, y, x) order
    lo = ijk * spacing
    rho = profile(lo[:, 0] + spacing[0] / 2).reshape(grid.shape)
    labels = Image(np.ones(grid.shape, np.int32), grid)
    interior = _interior(lo, lo + spacing, profile, size, r, rho_min)
    return World(density=Image(rho, grid), labels=labels), interior, r


def _ratio(result, interior, e_mev):
    """(ratio, σ) of the interior dose to the emitted energy per unit mass (module doc)."""
    sel = np.asarray(interior)
    expected = e_mev / result.mass_g.sum()
    per_batch = (result.energy_per_batch_mev[:, sel].sum(axis=1) / result.histories_per_batch
                 / result.mass_g[sel].sum() / expected)
    return per_batch.mean(), per_batch.std(ddof=1) / np.sqrt(len(per_batch))


def _run(kind, e_mev, n_hist, f_loss=0.25, n=12, cutoff=0.2):
    world, interior, _ = _phantom(kind, e_mev, n)
    plan = Plan(materials={1: "water", 2: "water", 3: "water"},
                volume_sources=(VolumeSource("electron", (e_mev,)),))
    settings = TransportSettings(n_histories=n_hist, n_batches=20, seed=5,
                                 energy_cutoff_mev=NO_PHOTONS_MEV,
                                 electron_cutoff_mev=min(cutoff, 0.5 * e_mev),
                                 max_energy_loss_fraction=f_loss)
    result = simulate(world, plan, settings, progress=False)
    return result, interior


@pytest.mark.parametrize("kind", ["mesh_linear", "voxel_linear", "mesh_steps", "voxel_steps"])
def test_fano_interior_dose_is_the_emitted_energy_per_mass(kind):
    result, interior = _run(kind, 1.0, 100_000)
    ratio, sigma = _ratio(result, interior, 1.0)
    assert np.count_nonzero(interior) > 50
    assert result.lost_photons == 0
    assert abs(ratio - 1.0) < max(4.0 * sigma, 0.005) and sigma < 0.01, (ratio, sigma)
    led = result.ledger
    assert led["electron_escaped_mev"] > 0.0  # the surface is reached: the test is not trivial
    closure = led["source_mev"] - sum(v for k, v in led.items() if k != "source_mev")
    assert abs(closure) < 1e-9


@pytest.mark.slow
@pytest.mark.parametrize("e_mev", [0.1, 1.0, 5.0])
@pytest.mark.parametrize("f_loss", [0.5, 0.25, 0.05])
@pytest.mark.parametrize("kind", ["mesh_linear", "voxel_linear", "mesh_steps", "voxel_steps"])
def test_fano_at_production_size(kind, f_loss, e_mev):
    result, interior = _run(kind, e_mev, 2_000_000, f_loss=f_loss, cutoff=min(0.2, 0.2 * e_mev))
    ratio, sigma = _ratio(result, interior, e_mev)
    assert result.lost_photons == 0
    assert sigma < 0.0015 and abs(ratio - 1.0) < 0.005, (ratio, sigma)
