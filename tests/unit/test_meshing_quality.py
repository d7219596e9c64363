"""Sliver repair after meshing: the fast min-dihedral formula, edge removal (3-2, 4-4, n→2n−4)
against a brute-force optimum, 2-3 flips, deletion of flat surface tetrahedra, and the whole
pass on planted slivers; the real masks reach 10° (slow)."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest

from tetdose.core import tetgrid
from tetdose.core.mesh import FACE_VERTICES, TetMesh, signed_volumes_mm3
from tetdose.meshing._relocation_kernels import min_dihedral_vol6
from tetdose.meshing.checks import conformity, dihedral_angles_deg
from tetdose.meshing.flips import flipped, tet_quality
from tetdose.meshing.quality import removed_slivers

DATA = Path(__file__).resolve().parents[3] / "shared" / "data"


def _surface_faces(tets: np.ndarray, region: np.ndarray) -> set[tuple[int, int, int, int, int]]:
    """Boundary and interface faces as (sorted vertices, own region, other region or −1)."""
    faces = tets[:, FACE_VERTICES].reshape(-1, 3)
    key = [tuple(sorted(f)) for f in faces.tolist()]
    owner: dict[tuple[int, ...], list[int]] = {}
    for i, k in enumerate(key):
        owner.setdefault(k, []).append(int(region[i // 4]))
    out = set()
    for k, regs in owner.items():
        if len(regs) == 1:
            out.add((*k, regs[0], -1))
        elif regs[0] != regs[1]:
            out.add((*k, max(regs), min(regs)))
    return out


def _check_same_polyhedron(points, tets0, tets1, region0, region1) -> None:  # noqa: ANN001
    """Positive cells, same total volume, same boundary and interface faces, conforming."""
    assert np.all(signed_volumes_mm3(points, tets1) > 0)
    for lab in np.unique(region0):
        np.testing.assert_allclose(signed_volumes_mm3(points, tets1[region1 == lab]).sum(),
                                   signed_volumes_mm3(points, tets0[region0 == lab]).sum(),
                                   rtol=1e-12)
    assert _surface_faces(tets1, region1) == _surface_faces(tets0, region0)
    conformity(TetMesh(points, tets1, region1))  # raises if a face has more than two cells


def _ring(n: int, h: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """n tetrahedra (a, b, r_i, r_{i+1}) around the edge a = (0,0,−h) … b = (0,0,h), the ring
    vertices jittered around the unit circle."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 2 * np.pi / n + rng.uniform(-0.3, 0.3, n) * np.pi / n
    ring = np.column_stack([np.cos(t), np.sin(t), rng.uniform(-0.3, 0.3, n)])
    ring[:, :2] *= rng.uniform(0.7, 1.3, (n, 1))
    points = np.vstack([[0.0, 0.0, -h], [0.0, 0.0, h], ring])
    tets = np.array([[0, 1, 2 + i, 2 + (i + 1) % n] for i in range(n)])
    return points, tets


def _triangulations(poly: tuple[int, ...]) -> list[list[tuple[int, int, int]]]:
    """Every triangulation of the convex-indexed polygon ``poly`` (brute force, Catalan many)."""
    if len(poly) < 3:
        return [[]]
    i, j = poly[0], poly[-1]
    out = []
    for m in range(1, len(poly) - 1):
        for left in _triangulations(poly[:m + 1]):
            for right in _triangulations(poly[m:]):
                out.append([*left, (i, poly[m], j), *right])
    return out


def test_min_dihedral_formula_matches_the_six_angles() -> None:
    rng = np.random.default_rng(3)
    points = rng.normal(size=(200, 3))
    tets = rng.integers(0, 200, size=(500, 4))
    tets = tets[np.array([len(set(t)) == 4 for t in tets.tolist()])]
    angle, vol6 = min_dihedral_vol6(points, tets)
    np.testing.assert_allclose(angle, dihedral_angles_deg(points, tets).min(axis=1), atol=1e-9)
    np.testing.assert_allclose(vol6 / 6.0, signed_volumes_mm3(points, tets), rtol=1e-12,
                               atol=1e-14)


@pytest.mark.parametrize("n", [3, 4, 5, 6])
def test_edge_removal_finds_the_best_triangulation_and_keeps_the_polyhedron(n: int) -> None:
    improved = 0
    for seed, h in itertools.product(range(6), (0.6, 1.2, 2.0)):
        points, tets = _ring(n, h, seed)
        q_old = tet_quality(points, tets).min()
        if not np.isfinite(q_old):  # the jitter folded the ring: not a valid mesh
            continue
        region = np.ones(len(tets), dtype=np.int64)
        new, new_region, _ = flipped(points, tets, region, q_old + 1.0)
        # brute force over every triangulation T of the ring: tets (a, T) and (b, T)
        best = -np.inf
        for tri in _triangulations(tuple(range(n))):
            r = np.asarray(tri) + 2
            cand = np.vstack([np.column_stack([np.zeros(len(r), int), r]),
                              np.column_stack([np.ones(len(r), int), r[:, [0, 2, 1]]])])
            best = max(best, tet_quality(points, cand).min())
        q_new = tet_quality(points, new).min()
        assert q_new >= q_old
        if best > q_old + 1e-6:  # removal pays: it must be taken, with the optimum
            improved += 1
            assert len(new) == 2 * n - 4
            assert q_new == pytest.approx(best, abs=1e-9)
        _check_same_polyhedron(points, tets, new, region, new_region)
    if n < 6:  # around 6 tets a better triangulation of these rings is rare
        assert improved > 0


def test_two_three_flip_raises_the_angle_of_two_flat_tets() -> None:
    h = 0.1
    points = np.array([[np.cos(t), np.sin(t), 0.0] for t in np.arange(3) * 2 * np.pi / 3]
                      + [[0.0, 0.0, -h], [0.0, 0.0, h]])
    tets = np.array([[0, 1, 2, 4], [0, 2, 1, 3]])
    region = np.array([5, 5])
    q_old = tet_quality(points, tets).min()
    assert q_old < 12.0
    new, new_region, left = flipped(points, tets, region, 12.0)
    assert len(new) == 3
    assert tet_quality(points, new).min() > 1.9 * q_old  # 2·atan(h/r_in) vs atan(h/r_in)
    _check_same_polyhedron(points, tets, new, region, new_region)
    # across an interface the face must stay: no new tetrahedron (flat ones may be deleted)
    same, _, _ = flipped(points, tets, np.array([5, 6]), 12.0)
    assert {tuple(t) for t in same.tolist()} <= {tuple(t) for t in tets.tolist()}


def test_flat_tet_on_the_outer_surface_is_deleted() -> None:
    """A unit cube (Kuhn, 6 tets) with its top diagonal p–r made a valley (q, s lifted by ε),
    capped by the flat tetrahedron (p, q, r, s) of another region: two of its faces are outer
    boundary, two an interface, so no flip may touch it (a flip inside one region would)."""
    eps = 0.02
    nodes = tetgrid.grid_nodes(np.zeros(3), np.ones(3), (1, 1, 1))
    tets = tetgrid.grid_tets((1, 1, 1), "kuhn")
    top = np.flatnonzero(np.isclose(nodes[:, 2], 1.0))
    faces = {tuple(sorted(f)) for f in tets[:, FACE_VERTICES].reshape(-1, 3).tolist()}
    diag = next((a, b) for a, b in itertools.combinations(top.tolist(), 2)
                if any({a, b} <= set(f) and set(f) <= set(top.tolist()) for f in faces)
                and np.linalg.norm(nodes[a] - nodes[b]) > 1.2)
    lifted = [v for v in top.tolist() if v not in diag]
    nodes = nodes.copy()
    nodes[lifted, 2] += eps
    cap = np.array([diag[0], lifted[0], diag[1], lifted[1]])
    if signed_volumes_mm3(nodes, cap[None])[0] < 0:
        cap = cap[[0, 2, 1, 3]]
    all_tets = np.vstack([tets, cap])
    region = np.r_[np.full(len(tets), 2), 1]
    assert tet_quality(nodes, all_tets).min() < 10.0
    new, new_region, _ = flipped(nodes, all_tets, region, 10.0)
    np.testing.assert_array_equal(new, tets)
    np.testing.assert_array_equal(new_region, 2)
    lost = signed_volumes_mm3(nodes, cap[None])[0]
    assert signed_volumes_mm3(nodes, new).sum() == pytest.approx(
        signed_volumes_mm3(nodes, all_tets).sum() - lost, rel=1e-12)
    assert lost < 0.01  # the cap is flat: ε/3 of the cube's top


def test_planted_slivers_in_two_regions_are_repaired() -> None:
    """A 6×6×6 Kuhn grid in two regions (x < 3 | x > 3) with vertices pushed to make slivers:
    every tet ends ≥ the threshold, interfaces and region volumes barely change."""
    cells = (6, 6, 6)
    nodes = tetgrid.grid_nodes(np.zeros(3), np.ones(3), cells)
    tets = tetgrid.grid_tets(cells, "kuhn")
    region = np.where(nodes[tets].mean(axis=1)[:, 0] < 3.0, 1, 2).astype(np.int64)
    rng = np.random.default_rng(0)
    pushed = nodes.copy()
    inner = np.flatnonzero(np.all((nodes > 0.5) & (nodes < 5.5), axis=1)
                           & ~np.isclose(nodes[:, 0], 3.0))
    for v in rng.choice(inner, 40, replace=False):
        trial = pushed.copy()
        trial[v] += rng.normal(scale=0.5, size=3)
        if np.all(signed_volumes_mm3(trial, tets) > 0):
            pushed = trial
    q0 = tet_quality(pushed, tets)
    assert (q0 < 12.0).sum() >= 10
    mesh0 = TetMesh(pushed, tets, region)
    points, new, new_region = removed_slivers(pushed, tets, region, 12.0)
    mesh = TetMesh(points, new, new_region)
    assert tet_quality(points, new).min() >= 12.0
    assert np.all(mesh.signed_volumes_mm3 > 0)
    for lab in (1, 2):  # free vertices move inside their region: volumes are exact
        np.testing.assert_allclose(mesh.volumes_mm3[new_region == lab].sum(),
                                   mesh0.volumes_mm3[region == lab].sum(), rtol=1e-9)
    assert _surface_faces(new, new_region) == _surface_faces(tets, region)
    np.testing.assert_allclose(points[np.isclose(nodes[:, 0], 3.0), 0], 3.0)  # in the plane
    assert conformity(mesh)["coincident_vertices"] == 0


def test_a_flip_never_adds_an_edge_or_face_the_mesh_already_has() -> None:
    """The 2-3 flip of (a,b,c,d) | (a,b,c,e) adds edge d-e: refused when a third tet already
    holds d and e (the new tets would overlap it), allowed otherwise; the same for a face."""
    from tetdose.meshing.flips import _fresh, _Mesh

    pts = np.random.default_rng(0).normal(size=(8, 3))
    a, b, c, d, e, x, y = range(7)
    pair = [(a, b, c, d), (a, b, c, e)]
    new = np.array([(d, e, a, b), (d, e, b, c), (d, e, c, a)])
    assert _fresh(_Mesh(pts, np.array(pair), np.ones(2, np.int64)), [0, 1], new)
    with_edge = np.array([*pair, (d, e, x, y)])
    assert not _fresh(_Mesh(pts, with_edge, np.ones(3, np.int64)), [0, 1], new)
    with_face = np.array([*pair, (d, e, a, 7)])
    assert not _fresh(_Mesh(pts, with_face, np.ones(3, np.int64)), [0, 1], new)
    unrelated = np.array([*pair, (d, x, y, 7)])
    assert _fresh(_Mesh(pts, unrelated, np.ones(3, np.int64)), [0, 1], new)


def test_a_faulty_topological_round_is_undone(monkeypatch) -> None:  # noqa: ANN001
    """If the flips ever returned a face shared by three tets (or an inverted tet), the pass
    keeps the topology it had and goes on by relocation alone: the output stays manifold."""
    from tetdose.meshing import flips, quality

    points, tets = _ring(5, 1.5, 1)
    region = np.ones(len(tets), dtype=np.int64)

    def faulty(points_mm, tets, region, min_dihedral_deg, bad=None):  # noqa: ANN001, ANN202
        return np.vstack([tets, tets[:1]]), np.r_[region, region[:1]], np.arange(len(tets) + 1)

    monkeypatch.setattr(flips, "flipped", faulty)
    assert not quality._valid_topology(points, np.vstack([tets, tets[:1]]))
    assert quality._valid_topology(points, tets)
    _, new, new_region = removed_slivers(points, tets, region, 40.0)
    np.testing.assert_array_equal(new, tets)  # the ring's topology, not the faulty one
    assert len(new_region) == len(tets)


def test_same_input_same_output() -> None:
    points, tets = _ring(5, 1.5, 1)
    region = np.ones(len(tets), dtype=np.int64)
    a = removed_slivers(points, tets, region, 40.0)
    b = removed_slivers(points, tets, region, 40.0)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)


@pytest.mark.slow
def test_real_mask_meshes_the_same_with_one_or_two_blas_threads() -> None:
    """MMG turned a last-bit difference of a threaded BLAS product into another mesh (the lung
    mask at 15 mm: meshes up to 0.23 mm apart with OPENBLAS_NUM_THREADS 1 and 2); the mesher now
    runs its numpy steps on one BLAS thread, so the mesh is the same whatever the caller's."""
    pytest.importorskip("mmgpy", reason="mmgpy not installed (extra tetdose[meshing])")
    path = DATA / "lung-elastix/3DCT_lung_baseline_mask.mha"
    if not path.is_file():
        pytest.skip(f"{path} not present (shared real data)")
    from threadpoolctl import threadpool_limits

    from tetdose.core.io import read_image
    from tetdose.meshing import conforming_mesh

    mask = read_image(path)
    labels = mask.with_array((np.asarray(mask.array) > 0).astype(np.int16))
    meshes = []
    for threads in (1, 2):
        with threadpool_limits(limits=threads, user_api="blas"):
            meshes.append(conforming_mesh(labels, [1], 15.0))
    np.testing.assert_array_equal(meshes[0].points_mm, meshes[1].points_mm)
    np.testing.assert_array_equal(meshes[0].tets, meshes[1].tets)


@pytest.mark.slow
@pytest.mark.parametrize(("path", "labels", "size"), [
    ("lung-elastix/3DCT_lung_baseline_mask.mha", [1], None),
    ("lung-elastix/3DCT_lung_baseline_mask.mha", [1], 8.0),
    ("abdomen-dicom/example_seg_dicom.nii.gz", [1, 5, 6], None),
])
def test_real_masks_reach_ten_degrees(path: str, labels: list[int], size: float | None) -> None:
    pytest.importorskip("mmgpy", reason="mmgpy not installed (extra tetdose[meshing])")
    if not (DATA / path).is_file():
        pytest.skip(f"{DATA / path} not present (shared real data)")
    from tetdose.core.io import read_image
    from tetdose.meshing import conforming_mesh, mesh_checks

    image = read_image(DATA / path)
    mesh = conforming_mesh(image, labels, size)
    report = mesh_checks(mesh, image, labels)
    assert report["min_dihedral_deg"] >= 10.0
    assert report["inverted"] == 0
    assert report["conformity"]["coincident_vertices"] == 0
    assert report["conformity"]["duplicated_boundary_faces"] == 0
    for entry in report["labels"].values():
        limit = 3.0 if entry["voxel_volume_cm3"] < 20 else 2.0
        assert abs(entry["volume_error_pct"]) <= limit
        assert entry["surface_distance_mean_mm"] < 1.0
