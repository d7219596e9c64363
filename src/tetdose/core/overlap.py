"""The sparse tetrahedron × voxel overlap: volumes Vol(V_j ∩ T_k) and barycentric moments.

For every pair (k, j) with a non-empty intersection I_kj = T_k ∩ V_j we keep
``bary_mm3[p, a] = ∫_{I_kj} λ_a dV`` [mm³], λ_a the barycentric coordinate of vertex a of T_k.
Their sum over a is Vol(I_kj) (Σλ = 1), so the paper's fractions are
F_kj = Vol(I_kj) / Vol(T_k) (eq. 7), and for a density linear in T_k with vertex values ρ_a the
mass in the voxel is Σ_a ρ_a · bary_mm3[p, a] (eq. 14–15, exact). The same moments give the
right-hand side of the L2 projection of the voxel density onto the mesh's P1 space.

Memory is proportional to the pairs (48 bytes each), never to grid × mesh: tetrahedra are
processed in chunks whose bounding-box pair counts stay under ``chunk_pairs``.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.sparse as sp
from tqdm.auto import tqdm

from tetdose._typing import FloatArray, IntArray
from tetdose.core import _montecarlo_kernels, _overlap_kernels, _tetsplit_kernels
from tetdose.core.image import ImageGrid
from tetdose.core.mesh import TetMesh
from tetdose.errors import GeometryMismatchError, OptionError

METHODS = ("exact", "monte-carlo")
#: Largest number of bounding-box pairs handled at once (bounds the scratch memory, ~48 B each).
CHUNK_PAIRS = 4_000_000


@dataclass(frozen=True, eq=False)
class Overlap:
    """Sparse tets × voxels intersection data in CSR layout (rows = tetrahedra)."""

    grid: ImageGrid
    tet_ptr: IntArray  # (M + 1,) row pointer
    voxel: IntArray  # (P,) flat voxel id of each pair
    bary_mm3: FloatArray  # (P, 4) ∫ λ_a over the intersection [mm³]
    method: str

    @property
    def n_tets(self) -> int:
        return len(self.tet_ptr) - 1

    @property
    def n_pairs(self) -> int:
        return len(self.voxel)

    @cached_property
    def volume_mm3(self) -> FloatArray:
        """(P,) Vol(T_k ∩ V_j) [mm³]."""
        return self.bary_mm3.sum(axis=1)

    @cached_property
    def tet(self) -> IntArray:
        """(P,) tetrahedron id of each pair."""
        return np.repeat(np.arange(self.n_tets), np.diff(self.tet_ptr))

    def volume_matrix_mm3(self) -> sp.csr_matrix:
        """Sparse (M, n_voxels) matrix of intersection volumes [mm³]."""
        return sp.csr_matrix((self.volume_mm3, self.voxel, self.tet_ptr),
                             shape=(self.n_tets, self.grid.n_voxels))

    def covered_volume_per_tet_mm3(self) -> FloatArray:
        """Volume of each tetrahedron that lies inside the image [mm³]."""
        return np.bincount(self.tet, weights=self.volume_mm3, minlength=self.n_tets)

    def covered_volume_per_voxel_mm3(self) -> FloatArray:
        """Volume of each voxel covered by the mesh [mm³], flat voxel order."""
        return np.bincount(self.voxel, weights=self.volume_mm3, minlength=self.grid.n_voxels)


def compute_overlap(mesh: TetMesh, grid: ImageGrid, *, method: str = "exact",
                    n_samples: int = 1000, seed: int = 0, progress: bool = False,
                    chunk_pairs: int = CHUNK_PAIRS) -> Overlap:
    """Intersect every tetrahedron of ``mesh`` with the voxels of ``grid``.

    ``method="exact"`` clips each tetrahedron against the voxel planes (default);
    ``"monte-carlo"`` is the paper's hit-and-miss estimate with ``n_samples`` points per
    tetrahedron (its error on F_kj is ~ sqrt(F(1−F)/n_samples)). Raises
    :class:`GeometryMismatchError` if no tetrahedron touches the image.
    """
    if method not in METHODS:
        raise OptionError(f"overlap method must be one of {METHODS}, got {method!r}")
    if method == "monte-carlo" and not int(n_samples) >= 1:
        raise OptionError(f"n_samples (CLI: --samples) must be ≥ 1 point per tetrahedron, got "
                          f"{n_samples}")
    u = grid.to_grid_frame(mesh.points_mm) / grid.spacing_mm
    u = np.ascontiguousarray(u)
    nx, ny, nz = grid.size
    span = _bbox_counts(u, mesh.tets, grid.size)
    chunks = _chunks(span, chunk_pairs)
    parts = []
    for lo, hi in tqdm(chunks, desc=f"overlap ({method})", unit="chunk", disable=not progress
                       or len(chunks) < 2):
        tets = np.ascontiguousarray(mesh.tets[lo:hi])
        offsets = np.zeros(hi - lo + 1, dtype=np.int64)
        np.cumsum(span[lo:hi], out=offsets[1:])
        n = int(offsets[-1])
        voxel, vol, cen = np.empty(n, np.int64), np.empty(n), np.empty((n, 3))
        count = np.zeros(hi - lo, dtype=np.int64)
        if method == "exact":
            if _overlap_kernels.overlap_exact(u, tets, nx, ny, nz, offsets, voxel, vol, cen,
                                              count):
                _tetsplit_kernels.overlap_tetsplit(u, tets, nx, ny, nz, offsets, voxel, vol,
                                                   cen, count, np.flatnonzero(count < 0))
        else:
            _montecarlo_kernels.overlap_monte_carlo(u, tets, nx, ny, nz, int(n_samples), int(seed) + lo,
                                        offsets, voxel, vol, cen, count)
        keep = np.repeat(offsets[:-1], count) + _ranks(count)
        parts.append((count, voxel[keep], vol[keep], cen[keep], lo, hi))
    counts = np.concatenate([p[0] for p in parts])
    tet_ptr = np.zeros(mesh.n_tets + 1, dtype=np.int64)
    np.cumsum(counts, out=tet_ptr[1:])
    voxel = np.concatenate([p[1] for p in parts])
    vol = np.concatenate([p[2] for p in parts])
    cen = np.concatenate([p[3] for p in parts])
    if len(voxel) == 0:
        lo_mm, hi_mm = mesh.bounds_mm()
        raise GeometryMismatchError(
            f"the mesh (bounding box {np.round(lo_mm, 1).tolist()} … {np.round(hi_mm, 1).tolist()}"
            " mm) lies wholly outside the image; check that both use patient coordinates in mm"
        )
    tet_of_pair = np.repeat(np.arange(mesh.n_tets), counts)
    bary = _barycentric(u, mesh.tets, tet_of_pair, cen) * vol[:, None] * grid.voxel_volume_mm3
    if method == "monte-carlo":
        # Sample means of λ_a are noisy; rescale them so each vertex's moments sum to covered/4,
        # as they do exactly (∫_T λ_a = V/4). F_kj itself (the paper's estimator) is unchanged.
        per_vertex = np.zeros((mesh.n_tets, 4))
        np.add.at(per_vertex, tet_of_pair, bary)
        target = per_vertex.sum(axis=1, keepdims=True) / 4.0
        bary *= (target / np.where(per_vertex > 0, per_vertex, 1.0))[tet_of_pair]
    return Overlap(grid, tet_ptr, voxel, bary, method)


def warn_if_uncovered(mesh: TetMesh, overlap: Overlap, *, tol: float = 1e-9) -> float:
    """Warn with the fraction of the mesh volume outside the image; return that fraction."""
    total = mesh.volumes_mm3.sum()
    outside = max(0.0, 1.0 - overlap.covered_volume_per_tet_mm3().sum() / total)
    if outside > tol:
        warnings.warn(
            f"{100 * outside:.3g} % of the mesh volume lies outside the image; densities there "
            "come only from the part inside (extend the image or crop the mesh)",
            stacklevel=3,
        )
    return outside


def _bbox_counts(u: FloatArray, tets: IntArray, size: tuple[int, int, int]) -> IntArray:
    """Voxels in each tetrahedron's clipped bounding box (an upper bound on its pair count)."""
    p = u[tets]
    lo = np.floor(p.min(axis=1) + 0.5).astype(np.int64)
    hi = np.floor(p.max(axis=1) + 0.5).astype(np.int64)
    lo = np.maximum(lo, 0)
    hi = np.minimum(hi, np.array(size) - 1)
    return np.prod(np.maximum(hi - lo + 1, 0), axis=1)


def _chunks(span: IntArray, limit: int) -> list[tuple[int, int]]:
    bounds = [0]
    acc = np.cumsum(span)
    while bounds[-1] < len(span):
        base = acc[bounds[-1] - 1] if bounds[-1] else 0
        nxt = int(np.searchsorted(acc, base + limit, side="right"))
        bounds.append(max(nxt, bounds[-1] + 1))
    return list(zip(bounds[:-1], bounds[1:], strict=True))


def _ranks(count: IntArray) -> IntArray:
    """0, 1, …, c−1 for each c in count, concatenated."""
    total = int(count.sum())
    starts = np.repeat(np.cumsum(count) - count, count)
    return np.arange(total) - starts


def _barycentric(u: FloatArray, tets: IntArray, tet_of_pair: IntArray, x: FloatArray
                 ) -> FloatArray:
    """(P, 4) barycentric coordinates of points x (index space) in their tetrahedra."""
    a = u[tets[:, 0]]
    edges = np.stack([u[tets[:, 1]] - a, u[tets[:, 2]] - a, u[tets[:, 3]] - a], axis=2)
    inv = np.linalg.inv(edges)  # (M, 3, 3)
    lam = np.einsum("pij,pj->pi", inv[tet_of_pair], x - a[tet_of_pair])
    return np.column_stack([1.0 - lam.sum(axis=1), lam])
