"""Structured tetrahedral meshes without an external mesher, and region-interface smoothing.

A box is cut into a grid of hexahedral cells, each split into tetrahedra by a fixed template:

* **Kuhn / Freudenthal** (6 tets per cell): one tetrahedron per permutation σ of the axes, with
  vertices on the monotone path 000 → e_σ1 → e_σ1+e_σ2 → 111. Every square face is cut by the
  diagonal through its lowest and highest corner in every cell, so the mesh is conforming.
  (H. W. Kuhn, "Some combinatorial lemmas in topology", IBM J. Res. Dev. 4 (1960) 518–524.)
* **Five-tetrahedra split**: a central tetrahedron on the four corners of one parity and four
  corner tetrahedra; cells alternate the parity like a checkerboard, so every face diagonal joins
  two nodes of even global parity and neighbouring cells conform.

Interface vertices are classified by the one region interface (or the outer boundary) they lie
on, so that a caller can move them within it; :func:`guarded` undoes any move that would shrink
a tetrahedron below a fraction of its volume, so every cell stays positively oriented.
"""

from __future__ import annotations

import numpy as np

from tetdose.core.mesh import signed_volumes_mm3

#: Local corner c of a cell sits at offset ((c >> 0) & 1, (c >> 1) & 1, (c >> 2) & 1).
_CORNERS = np.array([[(c >> a) & 1 for a in range(3)] for c in range(8)], dtype=np.float64)
#: Face i of a tetrahedron: the other three vertices (orientation irrelevant here).
_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]], dtype=np.intp)


def _oriented(template: list[list[int]]) -> np.ndarray:
    """Reorder each template tetrahedron so its signed volume in the unit cube is positive."""
    out = np.array(template, dtype=np.intp)
    p = _CORNERS[out]
    vol = np.einsum("ij,ij->i", p[:, 1] - p[:, 0], np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]))
    out[vol < 0] = out[vol < 0][:, [0, 2, 1, 3]]
    return out


def _kuhn_template() -> np.ndarray:
    perms = [(0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)]
    return _oriented([[0, 1 << a, (1 << a) | (1 << b), 7] for a, b, _ in perms])


def _five_template(parity: int) -> np.ndarray:
    """Central tet on the corners with bit-parity ``parity``; one corner tet at each other one."""
    central = [c for c in range(8) if bin(c).count("1") % 2 == parity]
    corners = [c for c in range(8) if bin(c).count("1") % 2 != parity]
    return _oriented([central] + [[c, c ^ 1, c ^ 2, c ^ 4] for c in corners])


KUHN = _kuhn_template()
FIVE_EVEN, FIVE_ODD = _five_template(0), _five_template(1)


def grid_nodes(start: np.ndarray, edge: np.ndarray, cells: tuple[int, int, int]) -> np.ndarray:
    """Node coordinates ``start + (i, j, k) * edge`` with node id ``(k*(ny+1) + j)*(nx+1) + i``."""
    nx, ny, nz = cells
    k, j, i = np.meshgrid(np.arange(nz + 1), np.arange(ny + 1), np.arange(nx + 1), indexing="ij")
    idx = np.stack([i.ravel(), j.ravel(), k.ravel()], axis=1).astype(np.float64)
    return start + idx * edge


def grid_tets(cells: tuple[int, int, int], scheme: str = "kuhn") -> np.ndarray:
    """(6 or 5 × n_cells, 4) node ids of the split cells (scheme ``"kuhn"`` or ``"five"``)."""
    nx, ny, nz = cells
    k, j, i = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    i, j, k = i.ravel(), j.ravel(), k.ravel()
    node = (
        ((k[:, None] + _CORNERS[None, :, 2].astype(np.intp)) * (ny + 1)
         + j[:, None] + _CORNERS[None, :, 1].astype(np.intp)) * (nx + 1)
        + i[:, None] + _CORNERS[None, :, 0].astype(np.intp)
    )  # (n_cells, 8) node id of each local corner
    if scheme == "kuhn":
        return node[:, KUHN].reshape(-1, 4)
    odd = ((i + j + k) % 2).astype(bool)
    per_cell = np.where(odd[:, None, None], node[:, FIVE_ODD], node[:, FIVE_EVEN])
    return per_cell.reshape(-1, 4)


def _interface_faces(tets: np.ndarray, region: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Faces between different regions or on the boundary, once each, with a code per pair."""
    faces = np.sort(tets[:, _FACES].reshape(-1, 3), axis=1)
    order = np.lexsort(faces.T[::-1])
    same = np.all(faces[order][1:] == faces[order][:-1], axis=1)
    other = np.full(len(faces), -1, dtype=np.int64)
    first, second = order[:-1][same], order[1:][same]
    own = np.repeat(region, 4)
    other[first], other[second] = own[second], own[first]
    keep = own > other  # interior interfaces once (higher label side); boundary (−1) always
    n_codes = int(region.max()) + 2
    return faces[keep], own[keep] * n_codes + other[keep] + 1


def surface_vertices(n_points: int, tets: np.ndarray, region: np.ndarray) -> np.ndarray:
    """Per-vertex interface code: −1 off the interfaces or on a junction of several of them.

    The code of an interface between regions a > b is ``a · (max + 2) + b + 1``; the outer
    boundary has b = −1.
    """
    faces, codes = _interface_faces(tets, region)
    vc = np.unique(np.stack([faces.ravel(), np.repeat(codes, 3)], axis=1), axis=0)
    n_codes = np.bincount(vc[:, 0], minlength=n_points)
    vertex_code = np.full(n_points, -1, dtype=np.int64)
    single = n_codes[vc[:, 0]] == 1
    vertex_code[vc[single, 0]] = vc[single, 1]
    return vertex_code


def guarded(old: np.ndarray, new: np.ndarray, tets: np.ndarray, vol0: np.ndarray,
            min_volume_frac: float) -> np.ndarray:
    """``new`` with the vertices of every cell whose volume fell below ``min_volume_frac`` ×
    ``vol0`` restored to ``old``, repeatedly; ends since restoring all gives back ``old``."""
    new = new.copy()
    bad = signed_volumes_mm3(new, tets) < min_volume_frac * vol0
    while bad.any():
        ids = np.unique(tets[bad])
        new[ids] = old[ids]
        bad = signed_volumes_mm3(new, tets) < min_volume_frac * vol0
    return new
