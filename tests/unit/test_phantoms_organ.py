"""Organ-shaped conforming phantom meshes (MMG); skipped without the ``meshing`` extra."""

from __future__ import annotations

import numpy as np
import pytest

from tetdose.errors import TetdoseError
from tetdose.phantoms import THORAX_MOVING, make_phantom, organ_mesh

pytest.importorskip("mmgpy", reason="mmgpy not installed (extra tetdose[meshing])")

from tetdose.meshing import conformity, mesh_checks  # noqa: E402


@pytest.fixture(scope="module")
def thorax():  # noqa: ANN201
    return make_phantom("thorax", seed=0, size="small")


@pytest.fixture(scope="module")
def moving(thorax):  # noqa: ANN001, ANN201
    return organ_mesh(thorax, THORAX_MOVING)


def test_thorax_lungs_and_tumour_one_conforming_mesh(thorax, moving) -> None:  # noqa: ANN001
    assert sorted(np.unique(moving.region).tolist()) == [3, 6]
    counts = conformity(moving)
    assert counts["coincident_vertices"] == 0 and counts["interface_faces"] > 0
    # The tumour sits inside the right lung: none of its faces is on the outer surface.
    k, _ = np.nonzero(moving.neighbors < 0)
    assert not np.any(moving.region[k] == 6)
    arr = thorax.labels.array
    vox = thorax.labels.grid.voxel_volume_mm3
    for region, labels in THORAX_MOVING.items():
        voxel = np.isin(arr, labels).sum() * vox
        mesh_volume = moving.volumes_mm3[moving.region == region].sum()
        assert mesh_volume == pytest.approx(voxel, rel=0.03), region
    assert (moving.signed_volumes_mm3 > 0).all()


def test_organ_mesher_option_of_make_phantom() -> None:
    p = make_phantom("liver", seed=1, size="small", mesher="organ")
    report = mesh_checks(p.mesh, p.labels, [2])
    assert set(np.unique(p.mesh.region)) == {2}
    assert abs(report["labels"]["2"]["volume_error_pct"]) < 2.0
    # Smooth: far fewer axis-aligned boundary normals than a staircase (all of them).
    f = p.mesh.points_mm[p.mesh.boundary_faces]
    n = np.cross(f[:, 1] - f[:, 0], f[:, 2] - f[:, 0])
    n = np.abs(n / np.linalg.norm(n, axis=1)[:, None])
    assert (n.max(axis=1) > 0.99).mean() < 0.2
    with pytest.raises(TetdoseError, match="unknown mesher"):
        make_phantom("liver", size="small", mesher="gmsh")


def test_study_mesh_sizes_by_name_coarsen_the_tumour_only_as_asked(thorax, moving) -> None:  # noqa: ANN001
    """`tetdose demo --size-mm tumour=H`: a larger target edge gives fewer, larger tumour tets
    whose union keeps the label's volume; a name that is not meshed is refused, naming those
    that are."""
    from tetdose.study import MOVING
    from tetdose.study import organ_mesh as study_mesh

    tumour = 6
    coarse = study_mesh(thorax, MOVING, {"tumour": 20.0})
    fine = moving.region == tumour
    big = coarse.region == tumour
    assert big.sum() < 0.8 * fine.sum()
    assert np.median(coarse.volumes_mm3[big]) > 1.2 * np.median(moving.volumes_mm3[fine])
    voxel = np.isin(thorax.labels.array, THORAX_MOVING[tumour]).sum() \
        * thorax.labels.grid.voxel_volume_mm3
    assert coarse.volumes_mm3[big].sum() == pytest.approx(voxel, rel=0.05)
    with pytest.raises(TetdoseError, match="no meshed structure named liver.*lung, tumour"):
        study_mesh(thorax, MOVING, {"liver": 10.0})
    with pytest.raises(TetdoseError, match="positive mm"):
        study_mesh(thorax, MOVING, {"tumour": -1.0})
