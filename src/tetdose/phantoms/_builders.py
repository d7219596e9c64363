"""The four procedural phantoms: label image → CT (HU) → structured multi-region mesh.

Patient frame LPS [mm]: +x towards the patient's left, +y posterior, +z superior; identity
direction; the grid is centred on the origin. CT values are the label's mean HU plus a smooth
heterogeneity field (Gaussian random field, correlation length in voxels), a Gaussian blur of
``PARTIAL_VOLUME_SIGMA_VOX`` (partial volume of a real scanner), then white noise; rounded to
int16 and clipped to [−1024, 3000] HU.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from tetdose.core import tetgrid
from tetdose.core.image import Image, ImageGrid
from tetdose.core.mesh import TetMesh
from tetdose.errors import TetdoseError
from tetdose.phantoms import _shapes
from tetdose.phantoms._meshing import mesh_labels

HU_MIN, HU_MAX = -1024, 3000
PARTIAL_VOLUME_SIGMA_VOX = 0.6
#: Independent random streams of one seed.
STREAM_NOISE, STREAM_HETEROGENEITY, STREAM_VESSELS = 1, 2, 3

Parts = tuple[Image, Image, TetMesh, dict[int, str], dict[int, str]]


def _rng(seed: int, stream: int) -> np.random.Generator:
    return np.random.default_rng([int(seed), stream])


def centred_grid(extent_mm: tuple[float, float, float], spacing_mm: float
                 ) -> tuple[ImageGrid, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Grid of about ``extent_mm`` centred on the origin; voxel centres x, y, z (nz, ny, nx)."""
    size = tuple(max(1, round(e / spacing_mm)) for e in extent_mm)
    spacing = np.full(3, float(spacing_mm))
    origin = -0.5 * (np.array(size) - 1) * spacing
    grid = ImageGrid(origin, spacing, np.eye(3), size)
    axes = [origin[a] + spacing[a] * np.arange(size[a]) for a in range(3)]
    z, y, x = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    return grid, (x, y, z)


def ct_from_labels(labels: np.ndarray, hu: dict[int, tuple[float, float]], seed: int, *,
                   noise_hu: float, correlation_vox: float = 3.0) -> np.ndarray:
    """HU image: mean_l + sd_l · smooth field, blurred, plus white noise (σ = ``noise_hu``)."""
    field = _shapes.smooth_noise(_rng(seed, STREAM_HETEROGENEITY), labels.shape, correlation_vox)
    mean = np.zeros(labels.shape)
    sd = np.zeros(labels.shape)
    for label, (m, s) in hu.items():
        mean[labels == label], sd[labels == label] = m, s
    img = _shapes.gaussian_filter(mean + sd * field, PARTIAL_VOLUME_SIGMA_VOX)
    img += noise_hu * _rng(seed, STREAM_NOISE).standard_normal(labels.shape)
    return np.clip(np.rint(img), HU_MIN, HU_MAX).astype(np.int16)


def cube(seed: int, *, n: int, spacing_mm: float, mean_hu: float, std_hu: float) -> Parts:
    """The paper's preliminary test: n³ random voxels under 2×2×1 hexahedra of 5 tets each."""
    if not 3 <= n <= 10:
        raise TetdoseError(f"cube size n must be in 3…10, got {n}; pass n=5 for the paper's case")
    grid, _ = centred_grid((n * spacing_mm,) * 3, spacing_mm)
    hu = _rng(seed, STREAM_NOISE).normal(mean_hu, std_hu, grid.shape)
    ct = np.clip(np.rint(hu), HU_MIN, HU_MAX).astype(np.int16)
    lo, hi = grid.bounds_grid_frame()
    nodes_q = tetgrid.grid_nodes(lo, (hi - lo) / np.array([2, 2, 1]), (2, 2, 1))
    mesh = TetMesh(grid.origin_mm + nodes_q, tetgrid.grid_tets((2, 2, 1), "five"),
                   np.ones(20, dtype=np.int64))
    labels = np.ones(grid.shape, dtype=np.uint8)
    return Image(ct, grid), Image(labels, grid), mesh, {1: "cube"}, {1: "soft_tissue"}


def _liver_shape(x: np.ndarray, y: np.ndarray, z: np.ndarray, centre: tuple[float, ...],
                 semi: tuple[float, float, float]) -> np.ndarray:
    """Deformed superellipsoid: tapering from the thick right lobe to the thin left lobe, bent."""
    a, b, c = semi
    u = np.clip((x - centre[0]) / a, -1.5, 1.5)  # −1 patient right … +1 left
    taper = 1.0 - 0.3 * (u + 1.0)  # height and depth shrink towards the left lobe
    yb = y - centre[1] - 0.25 * b * u**2  # posterior bend at both ends
    return (np.abs(u) ** 2.5 + np.abs(yb / (b * taper)) ** 2.5
            + np.abs((z - centre[2]) / (c * taper)) ** 2.5) <= 1.0


def liver(seed: int, *, spacing_mm: float, edge_mm: float, snap_iterations: int) -> Parts:
    """A liver-like organ (soft tissue ≈ 55 HU, mild heterogeneity) in a fat layer, in air."""
    grid, (x, y, z) = centred_grid((200.0, 170.0, 140.0), spacing_mm)
    labels = np.zeros(grid.shape, dtype=np.uint8)
    labels[_shapes.superellipsoid(x, y, z, (0, 0, 0), (92, 77, 62))] = 1
    labels[_liver_shape(x, y, z, (0.0, 0.0, 0.0), (75.0, 58.0, 48.0))] = 2
    hu = {0: (-1000.0, 2.0), 1: (-100.0, 6.0), 2: (55.0, 8.0)}
    ct = ct_from_labels(labels, hu, seed, noise_hu=8.0, correlation_vox=4.0)
    labels_img = Image(labels, grid)
    mesh = mesh_labels(labels_img, [2], edge_mm, snap_iterations=snap_iterations)
    return (Image(ct, grid), labels_img, mesh, {0: "air", 1: "fat", 2: "liver"},
            {0: "air", 1: "adipose", 2: "soft_tissue"})


def _paint_tree(labels: np.ndarray, coords: tuple[np.ndarray, ...], segments: list, label: int,
                where: np.ndarray, min_radius_mm: float) -> None:
    """Label the voxels of each tube (radius at least ``min_radius_mm``) that lie in ``where``."""
    x, y, z = coords
    axes = (x[0, 0, :], y[0, :, 0], z[:, 0, 0])
    for a, b, r in segments:
        r = max(r, min_radius_mm)
        lo, hi = np.minimum(a, b) - r, np.maximum(a, b) + r
        i0, j0, k0 = (int(np.searchsorted(ax, v)) for ax, v in zip(axes, lo, strict=True))
        i1, j1, k1 = (int(np.searchsorted(ax, v, side="right")) for ax, v in
                      zip(axes, hi, strict=True))
        box = (slice(k0, k1), slice(j0, j1), slice(i0, i1))
        tube = _shapes.capsule(x[box], y[box], z[box], a, b, r) & where[box]
        labels[box][tube] = label


def _tree(seed: int, lung_fn, root: tuple[float, ...], direction: tuple[float, ...],  # noqa: ANN001
          length_mm: float, radius_mm: float, stream_offset: int = 0) -> list:
    def inside(p: np.ndarray) -> bool:
        return bool(lung_fn(*(np.array([v]) for v in p))[0])

    rng = _rng(seed, STREAM_VESSELS + 10 * stream_offset)
    return _shapes.vessel_tree(rng, np.array(root, float), np.array(direction, float),
                               length_mm=length_mm, radius_mm=radius_mm, depth=5, inside=inside)


def lung(seed: int, *, spacing_mm: float, edge_mm: float, snap_iterations: int) -> Parts:
    """Lung parenchyma (≈ −850 HU) with a seeded vessel tree (≈ +40 HU) in a soft-tissue body."""
    grid, coords = centred_grid((170.0, 150.0, 180.0), spacing_mm)
    x, y, z = coords

    def lung_fn(x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
        return _shapes.superellipsoid(x, y, z, (0, 0, 0), (55, 45, 65), 2.2)

    labels = np.zeros(grid.shape, dtype=np.uint8)
    labels[_shapes.superellipsoid(x, y, z, (0, 0, 0), (75, 65, 82), 2.5)] = 1
    in_lung = lung_fn(x, y, z)
    labels[in_lung] = 2
    tree = _tree(seed, lung_fn, (-35.0, 0.0, 25.0), (1.0, 0.1, -0.4), 30.0, 5.0)
    _paint_tree(labels, coords, tree, 3, in_lung, 0.75 * spacing_mm)
    hu = {0: (-1000.0, 2.0), 1: (40.0, 6.0), 2: (-850.0, 20.0), 3: (40.0, 5.0)}
    ct = ct_from_labels(labels, hu, seed, noise_hu=12.0)
    labels_img = Image(labels, grid)
    mesh = mesh_labels(labels_img, [2, 3], edge_mm, snap_iterations=snap_iterations)
    return (Image(ct, grid), labels_img, mesh, {0: "air", 1: "body", 2: "lung", 3: "vessels"},
            {0: "air", 1: "soft_tissue", 2: "lung", 3: "blood"})


THORAX_LABELS = {0: "air", 1: "fat", 2: "muscle", 3: "lung", 4: "vessels", 5: "liver",
                 6: "tumour", 7: "bone", 8: "heart"}
THORAX_MATERIALS = {0: "air", 1: "adipose", 2: "muscle", 3: "lung", 4: "blood",
                    5: "soft_tissue", 6: "soft_tissue", 7: "cortical_bone", 8: "blood"}
#: Tumour centre [mm] in the lower right lung and its radius (2.5 cm diameter).
TUMOUR_CENTRE_MM = (-80.0, 5.0, -8.0)
TUMOUR_RADIUS_MM = 12.5


def _ribs_and_spine(x: np.ndarray, y: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rib bands (elliptic tubes sloping down anteriorly) and vertebral bodies with discs."""
    r_ell = np.sqrt((x / 148.0) ** 2 + (y / 96.0) ** 2)
    near_shell = np.abs(r_ell - 1.0) * 120.0 <= 5.0
    ribs = np.zeros(x.shape, dtype=bool)
    for z0 in range(-55, 100, 25):
        zc = z0 - 0.25 * (75.0 - y)
        ribs |= near_shell & (np.abs(z - zc) <= 5.0) & (y > -70.0)
    vertebra = ((x**2 + (y - 72.0) ** 2) <= 18.0**2) & (np.mod(z + 100.0, 28.0) >= 5.0)
    return ribs, vertebra


def thorax(seed: int, *, spacing_mm: float, edge_mm: float, snap_iterations: int) -> Parts:
    """Thorax section: fat, muscle, lungs with vessel trees, heart, liver, tumour, ribs, spine."""
    grid, coords = centred_grid((400.0, 300.0, 240.0), spacing_mm)
    x, y, z = coords
    body = _shapes.elliptic_cylinder(x, y, z, 170.0, 115.0, (-100.0, 100.0), 2.2)
    inner = _shapes.elliptic_cylinder(x, y, z, 158.0, 103.0, (-100.0, 100.0), 2.2)
    liver_m = _liver_shape(x, y, z, (-40.0, 5.0, -75.0), (95.0, 80.0, 50.0)) & inner
    heart = _shapes.superellipsoid(x, y, z, (18.0, -35.0, -5.0), (50.0, 45.0, 52.0))

    def lung_fn(side: float):  # noqa: ANN202 - closure over the lung's side
        def fn(x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
            shell = _shapes.superellipsoid(x, y, z, (75.0 * side, -5.0, 22.0), (55, 80, 72), 2.3)
            return (shell & ~_liver_shape(x, y, z, (-40.0, 5.0, -75.0), (95.0, 80.0, 50.0))
                    & ~_shapes.superellipsoid(x, y, z, (18.0, -35.0, -5.0), (50, 45, 52)))
        return fn

    labels = np.zeros(grid.shape, dtype=np.uint8)
    labels[body] = 1
    labels[inner] = 2
    lungs = lung_fn(-1.0)(x, y, z) | lung_fn(1.0)(x, y, z)
    labels[lungs] = 3
    for i, side in enumerate((-1.0, 1.0)):
        tree = _tree(seed, lung_fn(side), (28.0 * side, -5.0, 35.0), (side, 0.15, -0.35),
                     30.0, 5.0, stream_offset=i)
        _paint_tree(labels, coords, tree, 4, lungs, 0.75 * spacing_mm)
    labels[heart & inner] = 8
    labels[liver_m] = 5
    labels[_shapes.superellipsoid(x, y, z, TUMOUR_CENTRE_MM, (TUMOUR_RADIUS_MM,) * 3)] = 6
    ribs, vertebra = _ribs_and_spine(x, y, z)
    labels[(ribs & inner) | (vertebra & body)] = 7
    hu = {0: (-1000.0, 2.0), 1: (-100.0, 6.0), 2: (45.0, 6.0), 3: (-840.0, 25.0),
          4: (40.0, 5.0), 5: (60.0, 8.0), 6: (35.0, 10.0), 7: (700.0, 120.0), 8: (40.0, 5.0)}
    ct = ct_from_labels(labels, hu, seed, noise_hu=12.0)
    labels_img = Image(labels, grid)
    mesh = mesh_labels(labels_img, None, edge_mm, snap_iterations=snap_iterations)
    return Image(ct, grid), labels_img, mesh, dict(THORAX_LABELS), dict(THORAX_MATERIALS)


#: name → (builder, {size preset → parameters}).
BUILDERS: dict[str, tuple[Any, dict[str, dict[str, Any]]]] = {
    "cube": (cube, {s: {"n": 5, "spacing_mm": 1.0, "mean_hu": 50.0, "std_hu": 50.0}
                    for s in ("small", "medium")}),
    "liver": (liver, {"small": {"spacing_mm": 3.0, "edge_mm": 11.0, "snap_iterations": 3},
                      "medium": {"spacing_mm": 2.0, "edge_mm": 6.0, "snap_iterations": 3}}),
    "lung": (lung, {"small": {"spacing_mm": 3.0, "edge_mm": 11.0, "snap_iterations": 0},
                    "medium": {"spacing_mm": 2.0, "edge_mm": 6.0, "snap_iterations": 0}}),
    "thorax": (thorax, {"small": {"spacing_mm": 6.0, "edge_mm": 24.0, "snap_iterations": 0},
                        "medium": {"spacing_mm": 4.0, "edge_mm": 15.0, "snap_iterations": 0}}),
}
