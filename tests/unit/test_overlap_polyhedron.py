"""The polyhedron clipping of the exact overlap kernel, and its tetrahedra-splitting fallback.

- Primitives against analytic values: a tetrahedron's volume |det|/6 and centroid (vertex mean)
  for both orientations; the unit corner tetrahedron cut at x = a keeps the similar tetrahedron
  of scale 1 − a (volume (1 − a)³/6, centroid (a + (1 − a)/4, (1 − a)/4, (1 − a)/4)); clipping
  planes through a vertex or an edge; the neighbour graph stays symmetric (w ∈ nbr[v] ⇔
  v ∈ nbr[w]) after clips.
- The fallback: with a capacity too small for any clip every tetrahedron that needs clipping goes
  through the older tetrahedra splitting, an independent method; both give the same pairs.
"""

import numpy as np
import pytest

from tetdose.core import _overlap_kernels as k
from tetdose.core._tetsplit_kernels import overlap_tetsplit
from tetdose.core.overlap import _bbox_counts

CAP = 64
UNIT = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])


def scratch():
    return (np.empty((CAP, 3)), np.empty((CAP, 3), dtype=np.intp), np.empty(CAP),
            np.empty(CAP, dtype=np.intp), np.empty((CAP, 3), dtype=np.bool_), np.empty(4))


def moments(pos, nbr, n, marks, out):
    k._poly_moments(pos, nbr, n, marks, out)
    return out[0], out[1:] / out[0] if out[0] else out[1:]


def assert_symmetric_graph(nbr, n):
    for v in range(n):
        assert len(set(nbr[v])) == 3 and all(0 <= w < n for w in nbr[v])
        for w in nbr[v]:
            assert v in nbr[w]


@pytest.mark.parametrize("order", [[0, 1, 2, 3], [0, 1, 3, 2], [3, 1, 0, 2]])
def test_tetrahedron_volume_and_centroid_for_both_orientations(order):
    rng = np.random.default_rng(0)
    tet = rng.uniform(-3, 3, (4, 3))[order]
    pos, nbr, _, _, marks, out = scratch()
    n = k._poly_init(tet, pos, nbr)
    vol, cen = moments(pos, nbr, n, marks, out)
    det = np.linalg.det(tet[1:] - tet[0])
    assert vol == pytest.approx(abs(det) / 6, rel=1e-13)
    np.testing.assert_allclose(cen, tet.mean(axis=0), rtol=0, atol=1e-13)


@pytest.mark.parametrize("a", [0.1, 0.5, 0.9])
def test_cut_corner_tetrahedron_is_the_similar_tetrahedron(a):
    pos, nbr, sd, remap, marks, out = scratch()
    n = k._poly_init(UNIT, pos, nbr)
    n = k._poly_clip(pos, nbr, n, 0, a, -1.0, sd, remap)  # keep x ≥ a
    assert n == 4
    assert_symmetric_graph(nbr, n)
    vol, cen = moments(pos, nbr, n, marks, out)
    assert vol == pytest.approx((1 - a) ** 3 / 6, rel=1e-13)
    s = (1 - a) / 4
    np.testing.assert_allclose(cen, [a + s, s, s], atol=1e-14)
    # The complementary part (x ≤ a) is a frustum with 6 vertices and the rest of the volume.
    n2 = k._poly_init(UNIT, pos, nbr)
    n2 = k._poly_clip(pos, nbr, n2, 0, a, 1.0, sd, remap)
    assert n2 == 6
    assert_symmetric_graph(nbr, n2)
    assert moments(pos, nbr, n2, marks, out)[0] == pytest.approx(1 / 6 - (1 - a) ** 3 / 6,
                                                                 rel=1e-13)


def test_planes_through_a_vertex_or_an_edge():
    pos, nbr, sd, remap, marks, out = scratch()
    for axis, c in [(0, 0.0), (0, 1.0), (1, 1.0), (2, 0.0)]:  # face planes or through a vertex
        n_lo = k._poly_clip(pos, nbr, k._poly_init(UNIT, pos, nbr), axis, c, 1.0, sd, remap)
        lo = moments(pos, nbr, n_lo, marks, out)[0] if n_lo else 0.0
        n_hi = k._poly_clip(pos, nbr, k._poly_init(UNIT, pos, nbr), axis, c, -1.0, sd, remap)
        hi = moments(pos, nbr, n_hi, marks, out)[0] if n_hi else 0.0
        assert sorted([lo, hi]) == [0.0, pytest.approx(1 / 6, rel=1e-14)]
        assert 0 in (n_lo, n_hi)  # the empty side has no vertices, the other is untouched
    # The plane x = 0 through the edge (0, 1) halves this tetrahedron (volume 1/3) by symmetry.
    tet = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0], [1.0, 1.0, 0.0], [-1.0, 1.0, 0.0]])
    for sign in (1.0, -1.0):
        n = k._poly_clip(pos, nbr, k._poly_init(tet, pos, nbr), 0, 0.0, sign, sd, remap)
        assert_symmetric_graph(nbr, n)
        vol, cen = moments(pos, nbr, n, marks, out)
        assert vol == pytest.approx(1 / 6, rel=1e-14)
        np.testing.assert_allclose(cen, [-0.25 * sign, 0.5, 0.25], atol=1e-14)  # vertex mean


def test_overflow_is_reported():
    pos, nbr, sd, remap = np.empty((5, 3)), np.empty((5, 3), dtype=np.intp), np.empty(5), \
        np.empty(5, dtype=np.intp)
    n = k._poly_init(UNIT, pos, nbr)
    assert k._poly_clip(pos, nbr, n, 0, 0.5, 1.0, sd, remap) == -1  # needs 4 + 3 slots
    assert k._poly_clip(pos, nbr, -1, 1, 0.5, 1.0, sd, remap) == -1  # and passes it on


def run_kernel(u, tets, size, capacity):
    span = _bbox_counts(u, tets, size)
    off = np.zeros(len(tets) + 1, dtype=np.int64)
    np.cumsum(span, out=off[1:])
    n = int(off[-1])
    vox, vol, cen = np.empty(n, np.int64), np.empty(n), np.empty((n, 3))
    count = np.zeros(len(tets), dtype=np.int64)
    fallbacks = k.overlap_exact_capped(u, tets, *size, off, vox, vol, cen, count, capacity)
    assert np.count_nonzero(count < 0) == fallbacks
    if fallbacks:
        overlap_tetsplit(u, tets, *size, off, vox, vol, cen, count, np.flatnonzero(count < 0))
    keep = np.concatenate([np.arange(off[t], off[t] + count[t]) for t in range(len(tets))])
    return fallbacks, np.repeat(np.arange(len(tets)), count), vox[keep], vol[keep], cen[keep]


def test_fallback_to_tetrahedra_splitting_gives_the_same_pairs():
    """Random tets, a third of their coordinates snapped onto voxel planes, partly outside."""
    rng = np.random.default_rng(3)
    size = (9, 8, 7)
    centre = rng.uniform(-1, 9, (60, 1, 3))
    u = (centre + rng.normal(0, 2.0, (60, 4, 3))).reshape(-1, 3)
    snap = rng.random(u.shape) < 0.3
    u[snap] = np.round(u[snap] - 0.5) + 0.5
    tets = np.arange(len(u)).reshape(-1, 4).astype(np.intp)
    fb_poly, *poly = run_kernel(u, tets, size, CAP)
    fb_split, *split = run_kernel(u, tets, size, 4)
    assert fb_poly == 0 and fb_split > 40
    np.testing.assert_array_equal(poly[0], split[0])
    np.testing.assert_array_equal(poly[1], split[1])
    scale = np.abs(np.linalg.det(u[tets[:, 1:]] - u[tets[:, :1]])).max() / 6
    np.testing.assert_allclose(poly[2], split[2], rtol=0, atol=1e-12 * scale)
    # Centroids agree where a piece is not a round-off-sized sliver.
    big = poly[2] > 1e-6 * scale
    np.testing.assert_allclose(poly[3][big], split[3][big], rtol=0, atol=1e-6)
