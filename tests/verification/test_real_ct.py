"""Density mapping on real CT (paper §IV.C.2, Tables II–III): a lung and a liver.

Data in ``../shared/data`` (skipped when absent):

- ``lung-elastix``: a thorax CT (2.732×2.732×5 mm) and its lung mask on a finer grid
  (1.366×1.366×2.5 mm); the mask is resampled onto the CT grid by physical coordinates
  (nearest voxel centre) and meshed with :func:`tetdose.phantoms.mesh_labels`;
- ``abdomen-dicom``: a DICOM series (0.977×0.977×2 mm) and TotalSegmentator labels (5 = liver)
  on a y-flipped direction matrix: the liver is meshed on the label image's own grid (the mesher
  works in patient coordinates) and mapped onto the CT; the ROI is the labels resampled onto the
  CT grid by physical coordinates.

Fast tests use coarse meshes of a crop of each image; the full images are ``slow``. The figures
(RMDE, ESD, mass errors for each solver and overlap method) are printed by
``bench/bench_mapping.py real`` and recorded in ``bench/README.md``.

"Sane" RMDE is checked against an independent baseline: the best constant, i.e. the CT's mean
density over the mesh, reconstructed everywhere. A mapping must beat it.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

from tetdose.core.image import Image, ImageGrid
from tetdose.core.io import read_image
from tetdose.core.mesh import TetMesh
from tetdose.mapping import DensityMap, map_density
from tetdose.mapping.metrics import Evaluation, evaluate
from tetdose.phantoms import mesh_labels
from tetdose.phantoms._meshing import voxel_lookup

#: ../shared beside the repository root (tests/verification/<this file> → parents[2]).
SHARED = Path(__file__).resolve().parents[2].parent / "shared"
LUNG_CT = SHARED / "data" / "lung-elastix" / "3DCT_lung_baseline_small.mha"
LUNG_MASK = SHARED / "data" / "lung-elastix" / "3DCT_lung_baseline_mask.mha"
ABDOMEN_CT = SHARED / "data" / "abdomen-dicom" / "series"
ABDOMEN_SEG = SHARED / "data" / "abdomen-dicom" / "example_seg_dicom.nii.gz"
LIVER = 5
#: Soft tissue around the lung (HU above this, outside the lung mask) for the two-region mesh.
BODY_HU = -400


def _need(*paths: Path) -> None:
    missing = [str(p) for p in paths if not p.exists()]
    if missing:
        pytest.skip(f"real CT data not found ({', '.join(missing)}); it lives in ../shared/data "
                    "beside the checkout")


def resample_labels(labels: Image, grid: ImageGrid) -> Image:
    """Labels on ``grid``: the label voxel containing each voxel centre (physical coordinates).

    Nearest neighbour; 0 outside the label image. When both grids have the same axes up to sign
    (flipped included) the lookup is separable per axis; otherwise every centre is looked up.
    """
    rel = labels.grid.direction.T @ grid.direction
    if not np.allclose(np.abs(rel), np.eye(3), atol=1e-6):
        values = voxel_lookup(labels.grid, labels.array, grid.voxel_centers_mm())
        return Image(np.clip(values, 0, None).reshape(grid.shape).astype(labels.array.dtype), grid)
    start = labels.grid.physical_to_index(grid.origin_mm[None, :])[0]
    step = np.diag(rel) * grid.spacing_mm / labels.grid.spacing_mm
    idx = [np.floor(start[a] + step[a] * np.arange(grid.size[a]) + 0.5).astype(np.int64)
           for a in range(3)]
    ok = [(i >= 0) & (i < n) for i, n in zip(idx, labels.grid.size, strict=True)]
    picked = labels.array[np.ix_(*(np.where(o, i, 0) for o, i in zip(ok[::-1], idx[::-1],
                                                                      strict=True)))]
    inside = ok[2][:, None, None] & ok[1][None, :, None] & ok[0][None, None, :]
    return Image(np.where(inside, picked, 0).astype(labels.array.dtype), grid)


def crop(image: Image, lo: tuple[int, int, int], hi: tuple[int, int, int]) -> Image:
    """Sub-image of voxels lo ≤ (i, j, k) < hi with the same physical placement."""
    g = image.grid
    sub = ImageGrid(g.index_to_physical(np.array(lo, float)), g.spacing_mm, g.direction,
                    tuple(int(b - a) for a, b in zip(lo, hi, strict=True)))
    return Image(image.array[lo[2]:hi[2], lo[1]:hi[1], lo[0]:hi[0]], sub)


def run(mesh: TetMesh, ct: Image, roi: np.ndarray, **kw: object) -> tuple[DensityMap, Evaluation]:
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the meshes lie inside the CT: no uncovered-volume warning
        dm = map_density(mesh, ct, **kw)
    # The reconstruction always uses the exact overlap: a Monte Carlo one would add its own
    # sampling noise to every reconstructed voxel and hide the quality of the densities.
    exact = dm.overlap if dm.overlap.method == "exact" else None
    return dm, evaluate(ct, dm.mesh, dm.density_g_cm3, roi=roi, overlap=exact)


def constant_baseline_rmde(ev: Evaluation, dm: DensityMap, roi: np.ndarray) -> float:
    """RMDE [%] of reconstructing every ROI voxel with the CT mean density inside the mesh."""
    mean = dm.ct_mass_covered_g * 1000.0 / dm.mesh.volumes_mm3.sum()
    rho = ev.original.array[roi]
    return float(100.0 * np.mean(np.abs(rho - mean) / rho))


def check_l2_and_lsq(mesh: TetMesh, ct: Image, roi: np.ndarray, **kw: object
                     ) -> dict[str, tuple[DensityMap, Evaluation]]:
    """Assertions shared by every case; returns both mappings for case-specific checks."""
    out = {s: run(mesh, ct, roi, solver=s, **kw) for s in ("l2", "lsq")}
    (l2, ev_l2), (lsq, _) = out["l2"], out["lsq"]
    assert l2.outside_fraction < 1e-12
    assert l2.mass_error_covered < 1e-9  # mesh mass = CT mass inside the mesh
    assert ev_l2.metrics.mass_error_in_mesh_pct < 1e-7
    assert l2.density_g_cm3.min() >= 0.0
    assert l2.density_g_cm3.max() <= ev_l2.original.array.max() * (1 + 1e-12)
    assert lsq.mass_error_covered > l2.mass_error_covered  # the paper's solve loses some mass
    for (dm, ev) in out.values():
        assert ev.metrics.rmde_pct < constant_baseline_rmde(ev, dm, roi)
    return out


@pytest.fixture(scope="module")
def lung() -> tuple[Image, Image]:
    """(CT [HU], lung labels on the CT grid)."""
    _need(LUNG_CT, LUNG_MASK)
    ct = read_image(LUNG_CT)
    return ct, resample_labels(read_image(LUNG_MASK), ct.grid)


@pytest.fixture(scope="module")
def abdomen() -> tuple[Image, Image, Image]:
    """(CT [HU], labels on their own y-flipped grid, labels resampled onto the CT grid)."""
    _need(ABDOMEN_CT, ABDOMEN_SEG)
    ct = read_image(ABDOMEN_CT)
    seg = read_image(ABDOMEN_SEG)
    return ct, seg, resample_labels(seg, ct.grid)


def test_labels_are_mapped_by_physical_coordinates(lung, abdomen) -> None:  # noqa: ANN001
    _, mask_on_ct = lung
    ct, seg, seg_on_ct = abdomen
    assert np.linalg.det(seg.grid.direction) < 0 < np.linalg.det(ct.grid.direction)
    # The label image holds the same voxels in flipped y order.
    np.testing.assert_array_equal(seg_on_ct.array, seg.array[:, ::-1, :])
    # The lung mask grid is twice as fine; the separable lookup agrees with the pointwise one.
    mask = read_image(LUNG_MASK)
    pointwise = voxel_lookup(mask.grid, mask.array, mask_on_ct.grid.voxel_centers_mm())
    np.testing.assert_array_equal(mask_on_ct.array.ravel(), pointwise)
    assert 5e4 < int((mask_on_ct.array == 1).sum()) < 2e5


def test_lung_crop_coarse_mesh(lung) -> None:  # noqa: ANN001
    ct, labels = lung
    lo, hi = (0, 0, 22), (ct.grid.size[0], ct.grid.size[1], 44)
    ct, labels = crop(ct, lo, hi), crop(labels, lo, hi)
    roi = labels.array == 1
    mesh = mesh_labels(labels, [1], 15.0)
    out = check_l2_and_lsq(mesh, ct, roi)
    # RMDE is dominated by the many near-air voxels of the mask (ρ ≈ 0.001 g/cm³, where a small
    # absolute error is a huge relative one); the median relative error shows the l2 advantage.
    med = {s: float(np.median(ev.relative_error_pct.array[roi])) for s, (_, ev) in out.items()}
    assert med["l2"] < med["lsq"]


def test_liver_crop_coarse_mesh(abdomen) -> None:  # noqa: ANN001
    ct, _, labels = abdomen
    kji = np.nonzero(labels.array == LIVER)
    lo = (int(kji[2].min()), int(kji[1].min()), 4)
    hi = ((lo[0] + int(kji[2].max())) // 2, (lo[1] + int(kji[1].max())) // 2, 14)
    ct, labels = crop(ct, lo, hi), crop(labels, lo, hi)
    roi = labels.array == LIVER
    mesh = mesh_labels(labels, [LIVER], 10.0)
    out = check_l2_and_lsq(mesh, ct, roi)
    rmde = {s: ev.metrics.rmde_pct for s, (_, ev) in out.items()}
    assert rmde["l2"] < 3.0  # paper, Table II: 0.9–1.7 %
    # On the liver the two solves agree to ~0.1 % in RMDE (here lsq is 0.1 % lower): l2 buys
    # exact mass at no cost in accuracy. Asserted with a 1 % margin, not as l2 ≤ lsq.
    assert rmde["l2"] <= rmde["lsq"] * 1.01


@pytest.mark.slow
@pytest.mark.parametrize("edge_mm", [10.0, 5.0])
def test_lung_full(lung, edge_mm: float) -> None:  # noqa: ANN001
    ct, labels = lung
    roi = labels.array == 1
    out = check_l2_and_lsq(mesh_labels(labels, [1], edge_mm), ct, roi)
    med = {s: float(np.median(ev.relative_error_pct.array[roi])) for s, (_, ev) in out.items()}
    assert med["l2"] < med["lsq"]


@pytest.mark.slow
def test_lung_two_regions_keep_the_chest_wall_jump(lung) -> None:  # noqa: ANN001
    """Lung + surrounding soft tissue: duplicating vertices per region (by_region) lowers RMDE."""
    ct, labels = lung
    arr = labels.array.copy()
    arr[(arr == 0) & (ct.array > BODY_HU)] = 2
    two = Image(arr, ct.grid)
    roi = arr > 0
    mesh = mesh_labels(two, [1, 2], 10.0)
    _, joint = run(mesh, ct, roi)
    split_map, split = run(mesh, ct, roi, by_region=True)
    assert split_map.mass_error_covered < 1e-9
    assert split.metrics.rmde_pct < 0.9 * joint.metrics.rmde_pct


@pytest.mark.slow
@pytest.mark.parametrize("edge_mm", [8.0, 4.0])
def test_liver_full_on_the_flipped_label_grid(abdomen, edge_mm: float) -> None:  # noqa: ANN001
    ct, seg, labels = abdomen
    roi = labels.array == LIVER
    mesh = mesh_labels(seg, [LIVER], edge_mm)  # meshed in patient coordinates from the flipped grid
    out = check_l2_and_lsq(mesh, ct, roi)
    rmde = {s: ev.metrics.rmde_pct for s, (_, ev) in out.items()}
    assert rmde["l2"] < 2.0
    assert rmde["l2"] <= rmde["lsq"] * 1.01
    # The mesh follows the label voxels: eq. 23 (ROI voxel mass vs mesh mass) stays small.
    assert out["l2"][1].metrics.mass_error_pct < 1.0


@pytest.mark.slow
def test_liver_monte_carlo_overlap_approaches_exact(abdomen) -> None:  # noqa: ANN001
    ct, seg, labels = abdomen
    roi = labels.array == LIVER
    mesh = mesh_labels(seg, [LIVER], 8.0)
    exact_map, exact = run(mesh, ct, roi)
    mc_map, mc = run(mesh, ct, roi, overlap="monte-carlo", n_samples=2000)
    assert mc_map.mass_error_covered < 1e-9  # l2 conserves whatever overlap it is given
    assert abs(mc_map.ct_mass_covered_g / exact_map.ct_mass_covered_g - 1) < 1e-3
    assert abs(mc.metrics.rmde_pct - exact.metrics.rmde_pct) < 0.05 * exact.metrics.rmde_pct
