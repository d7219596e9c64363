"""Batched level-set cuts of the MMG mesher: labels apart from each other share one MMG call,
with the same cut as one label at a time; touching labels never share one."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tetdose.core.image import Image, ImageGrid
from tetdose.core.mesh import signed_volumes_mm3

pytest.importorskip("mmgpy", reason="mmgpy not installed (extra tetdose[meshing])")

from tetdose.meshing import mmg  # noqa: E402

PLAIN_NEXT_BATCH = mmg._next_batch

SPACING_MM = 2.0
#: Four balls apart from each other (labels 1–4) and two boxes touching face to face (5 | 6).
BALLS = {1: ((-23.0, -14.0, 0.0), 6.0), 2: ((-23.0, 14.0, 0.0), 7.0),
         3: ((0.0, -14.0, 0.0), 7.5), 4: ((0.0, 14.0, 0.0), 8.0)}
BOX5 = ((14.0, -14.0, -10.0), (26.0, 14.0, 10.0))
BOX6 = ((25.0, -14.0, -10.0), (38.0, 14.0, 10.0))


def _scene() -> Image:
    n = np.array([36, 24, 16])
    origin = -0.5 * (n - 1) * SPACING_MM + np.array([4.0, 0.0, 0.0])
    grid = ImageGrid(origin, (SPACING_MM,) * 3, np.eye(3), tuple(int(v) for v in n))
    c = grid.voxel_centers_mm()
    lab = np.zeros(len(c), dtype=np.uint8)
    for value, (centre, r) in BALLS.items():
        lab[np.linalg.norm(c - centre, axis=1) <= r] = value
    for value, (lo, hi) in ((5, BOX5), (6, BOX6)):
        lab[np.all((c > lo) & (c < hi), axis=1)] = value
    return Image(lab.reshape(grid.shape), grid)


@pytest.fixture(scope="module")
def stage():  # noqa: ANN201
    return mmg._prepared(mmg._mmg(), _scene(), None, 4.0, mmg.SMOOTHING_VOX, True)


def _cut_volumes(stage, batched: bool, monkeypatch) -> tuple[dict[int, float], list]:  # noqa: ANN001
    calls = []
    def spy(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        batch, psi = PLAIN_NEXT_BATCH(*args, **kwargs)
        calls.append(batch)
        return batch, psi

    monkeypatch.setattr(mmg, "_next_batch", spy)
    points, tets, refs = mmg._cut_labels(mmg._mmg(), stage.points, stage.tets, stage.phi,
                                         stage.order, batched=batched)
    vols = np.abs(signed_volumes_mm3(points, tets))
    return {lab: float(vols[refs == lab].sum()) for lab in stage.order}, calls


def test_batched_cut_equals_one_label_at_a_time(stage, monkeypatch) -> None:  # noqa: ANN001
    batched, calls = _cut_volumes(stage, True, monkeypatch)
    alone, single_calls = _cut_volumes(stage, False, monkeypatch)
    assert [len(b) for b in single_calls] == [1] * 6
    assert len(calls) < len(single_calls)
    assert set(calls[0]) >= {1, 2, 3, 4}  # the balls are apart: one call
    assert not any({5, 6} <= set(b) for b in calls)  # touching boxes: never together
    for lab in stage.order:
        assert batched[lab] == pytest.approx(alone[lab], rel=1e-9), lab


def test_touching_labels_cross_the_same_tetrahedra(stage) -> None:  # noqa: ANN001
    # The rule behind the batches: ψ_5 and ψ_6 change sign in common tetrahedra, so ψ_B = min
    # would move a crossing; the balls' crossed tetrahedra are disjoint.
    stage.phi.at(stage.points)
    batch, psi = mmg._next_batch(stage.phi, stage.tets, [5, 6], set())
    assert batch == [5]
    batch, psi = mmg._next_batch(stage.phi, stage.tets, [1, 2, 3, 4, 5, 6], set())
    assert {1, 2, 3, 4} <= set(batch) and not {5, 6} <= set(batch)
    # ψ_B < 0 exactly where one of the batch's labels is the nearest (its Voronoi cell).
    nearest = np.argmin([stage.phi.values[m] for m in range(7)], axis=0)
    np.testing.assert_array_equal(psi < 0, np.isin(nearest, batch))
    assert np.count_nonzero(psi < 0) > 100


#: The real TotalSegmentator-style map (31 labels, 512×512×20, y-flipped direction), read in place.
ABDOMEN_SEG = (Path(__file__).resolve().parents[2].parent / "shared" / "data" / "abdomen-dicom"
               / "example_seg_dicom.nii.gz")


@pytest.mark.slow
def test_every_label_of_a_real_segmentation_meshes_with_its_checks() -> None:
    if not ABDOMEN_SEG.exists():
        pytest.skip(f"{ABDOMEN_SEG} not found: the real label map lives in ../shared/data")
    from tetdose.core.io import read_image
    from tetdose.meshing import conforming_mesh, mesh_checks

    seg = read_image(ABDOMEN_SEG)
    ids = np.unique(seg.array[seg.array > 0]).tolist()
    assert len(ids) == 31
    mesh = conforming_mesh(seg)  # every label, default sizes
    report = mesh_checks(mesh, seg)
    assert sorted(np.unique(mesh.region).tolist()) == ids  # every label kept, the 0.2 cm³ ones too
    for lab, entry in report["labels"].items():
        limit = 3.0 if entry["voxel_volume_cm3"] < 20 else 2.0
        assert abs(entry["volume_error_pct"]) <= limit, (lab, entry["volume_error_pct"])
        assert entry["surface_distance_mean_mm"] < 1.0, lab  # about a voxel at most
    conf = report["conformity"]
    assert conf["coincident_vertices"] == 0 and conf["duplicated_boundary_faces"] == 0
    assert conf["interface_faces"] > 0  # touching organs share faces
    assert report["inverted"] == 0
