"""TetMesh refuses regions that touch through duplicated (coincident) vertices, and merges them."""

from __future__ import annotations

import numpy as np
import pytest

from tetdose.core import tetgrid
from tetdose.core.mesh import TetMesh
from tetdose.errors import MeshError


def _two_blocks(shared: bool) -> TetMesh:
    """Two 2×2×2-cell Kuhn blocks side by side along x (regions 1, 2); their touching face shares
    vertices when ``shared``, else each block has its own copies of them."""
    pts = tetgrid.grid_nodes(np.zeros(3), np.ones(3), (4, 2, 2))
    tets = tetgrid.grid_tets((4, 2, 2))
    region = np.where(pts[tets].mean(axis=1)[:, 0] < 2.0, 1, 2)
    if shared:
        return TetMesh(pts, tets, region)
    on_face = np.isclose(pts[:, 0], 2.0)
    copy_id = np.full(len(pts), -1)
    copy_id[on_face] = len(pts) + np.arange(on_face.sum())
    tets = tets.copy()
    right = region == 2
    t = tets[right]
    tets[right] = np.where(on_face[t], copy_id[t], t)
    return TetMesh(np.concatenate([pts, pts[on_face]]), tets, region)


def test_duplicated_interface_vertices_are_refused_with_count_and_fix() -> None:
    mesh = _two_blocks(shared=False)
    assert mesh.coincident_vertices().size == 9
    with pytest.raises(MeshError, match=r"9 vertices coincide.*merged_duplicates\(\)"):
        _ = mesh.neighbors


def test_merged_duplicates_gives_the_conforming_mesh() -> None:
    merged = _two_blocks(shared=False).merged_duplicates()
    ref = _two_blocks(shared=True)
    assert merged.n_points == ref.n_points
    assert merged.coincident_vertices().size == 0
    # The interface is now interior: as many boundary faces as the conforming mesh has.
    assert len(merged.boundary_faces) == len(ref.boundary_faces) == 2 * (8 + 8 + 4) * 2
    np.testing.assert_allclose(np.sort(merged.volumes_mm3), np.sort(ref.volumes_mm3))


def test_region_split_copies_are_not_refused() -> None:
    split = _two_blocks(shared=True).split_by_region()  # parent_point links the copies
    assert split.coincident_vertices().size == 9
    assert (split.neighbors >= 0).sum() == (_two_blocks(shared=True).neighbors >= 0).sum()
