"""Geometry kernels of the transport: tet walker, mesh entry, voxel traversal, vs brute force.

Path lengths per cell are read through the track-length tally of a flight that never interacts
(τ = ∞): it adds E·(μen/ρ)·∫ρ ds per cell, so with E = 1 and dividing by μen/ρ it returns the
column density ∫ρ ds [mm·g/cm³] through each cell, which the references compute independently
(half-space clipping of the ray against every cell, pure Python/numpy).
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from tetdose._constants import MM_PER_CM
from tetdose.core.image import Image, ImageGrid
from tetdose.core.mesh import FACE_VERTICES, TetMesh
from tetdose.transport import mesh_geometry, morton_order
from tetdose.transport.geometry._tet import LOCATE_TOL_MM, enter_mesh, exit_face, locate_point
from tetdose.transport.geometry._voxel import VoxelGeometry
from tetdose.transport.geometry._world import start_cell
from tetdose.transport.geometry.world import voxel_world
from tetdose.transport.history._photon import C_CROSSINGS, ESCAPES, N_COUNTS, flight_mesh, flight_voxel
from tetdose.transport.physics._photon import transport_coefficients
from tetdose.transport.physics.xs import build_cross_sections

import helpers
from helpers import ray_interval


def box_mesh(n, size_mm, origin_mm=(0.0, 0.0, 0.0), jitter=0.0, seed=0):
    """Structured box of n cubes per axis (6 Kuhn tets each), by size and origin [mm]."""
    lo = np.asarray(origin_mm, dtype=float)
    return helpers.box_mesh(lo, lo + np.asarray(size_mm, dtype=float), n, jitter=jitter, seed=seed)


@pytest.fixture(scope="module")
def xs():
    return build_cross_sections(["water"])


def _column_per_cell_mesh(g, xs, k, p, d, n_cells):
    tally = np.zeros(n_cells)
    counts = np.zeros(N_COUNTS, dtype=np.int64)
    out, *_ = flight_mesh(g, xs, 1.0, k, -1, *p, *d, 1e300, True, tally, counts)
    mu_en = transport_coefficients(xs, 0, 1.0)[1]
    return out, tally * MM_PER_CM / mu_en, counts


def _reference_chords(mesh, rho, p, d):
    """{tet: (t_in, t_out, ∫ρ ds)} for tets the ray p + t·d (t ≥ 0) crosses with length > 0."""
    out = {}
    for k, tet in enumerate(mesh.tets):
        v = mesh.points_mm[tet]
        t_in, t_out = ray_interval(v, p, d)
        if t_out - t_in > 1e-9:
            mid = p + 0.5 * (t_in + t_out) * d
            bary = np.linalg.solve(np.vstack([v.T, np.ones(4)]), np.append(mid, 1.0))
            out[k] = (t_in, t_out, (t_out - t_in) * float(bary @ rho[tet]))
    return out


def test_kernel_planes_are_float32_one_per_shared_face_and_through_the_vertices():
    # far from the origin, where float32 offsets round most (|c| up to 640 mm)
    mesh = box_mesh((3, 3, 3), (30.0, 30.0, 30.0), origin_mm=(-600.0, 250.0, 400.0), jitter=0.25)
    g = mesh_geometry(mesh, np.ones(mesh.n_points), np.zeros(mesh.n_tets, dtype=np.intp))
    assert g.planes.dtype == np.float32 and g.link.dtype == np.int32
    assert g.planes.ctypes.data % 64 == 0  # one tet's planes: one cache line
    k, f = np.nonzero(g.link >= 0)
    k2, f2 = g.link[k, f] >> 2, g.link[k, f] & 3
    np.testing.assert_array_equal(g.planes[k2, f2], -g.planes[k, f])  # every point on one side
    pl = g.planes.astype(np.float64)
    assert np.all(np.abs(np.linalg.norm(pl[..., :3], axis=2) - 1.0) < 2e-7)
    verts = mesh.points_mm[mesh.tets[:, FACE_VERTICES]]  # (M, 4, 3 vertices, 3)
    miss = np.einsum("mfi,mfvi->mfv", pl[..., :3], verts) - pl[..., 3:]
    # the offset's rounding (2⁻²⁴|c|) and the normal's over an edge (2⁻²⁴·√3·15 mm)
    assert np.abs(miss).max() <= 2.0**-24 * np.abs(pl[..., 3]).max() + 2.0**-24 * 30.0
    # each tet's own centroid is strictly inside its planes
    cen = mesh.points_mm[mesh.tets].mean(axis=1)
    assert np.all(np.einsum("mfi,mi->mf", pl[..., :3], cen) - pl[..., 3] < -0.1)


def test_walker_matches_brute_force_on_random_rays(xs):
    mesh = box_mesh((3, 3, 3), (30.0, 30.0, 30.0), jitter=0.25)
    rng = np.random.default_rng(1)
    rho = rng.uniform(0.5, 1.5, mesh.n_points)
    g = mesh_geometry(mesh, rho, np.zeros(mesh.n_tets, dtype=np.intp))
    for _ in range(40):
        k = int(rng.integers(mesh.n_tets))
        p = mesh.points_mm[mesh.tets[k]].T @ rng.dirichlet(np.ones(4))
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        out, col, counts = _column_per_cell_mesh(g, xs, k, p, d, mesh.n_tets)
        ref = _reference_chords(mesh, rho, p, d)
        expected = np.zeros(mesh.n_tets)
        for kk, (_, _, c) in ref.items():
            expected[kk] = c
        assert out == ESCAPES and counts[1] == 0
        assert counts[C_CROSSINGS] == len(ref)  # one crossing per tet left
        # the kernel's face planes are float32: within 2⁻²⁴·|c| (< 3·10⁻⁶ mm here) of the vertices
        np.testing.assert_allclose(col, expected, atol=1e-5)


def test_tet_order_does_not_change_the_walk(xs):
    """Kernel tet i = mesh tet order[i]: a renumbered geometry walks the same chords."""
    mesh = box_mesh((3, 3, 3), (30.0, 30.0, 30.0), jitter=0.25, seed=5)
    rng = np.random.default_rng(6)
    rho = rng.uniform(0.5, 1.5, mesh.n_points)
    material = np.zeros(mesh.n_tets, dtype=np.intp)
    orders = {"identity": np.arange(mesh.n_tets), "random": rng.permutation(mesh.n_tets),
              "morton": morton_order(mesh.centroids_mm)}
    assert sorted(orders["morton"]) == list(range(mesh.n_tets))
    d = np.array([1.0, 0.4, 0.3]) / np.sqrt(1.25)
    cols = {}
    for name, order in orders.items():
        g = mesh_geometry(mesh, rho, material, order)
        k, x, y, z, _ = enter_mesh(g, -5.0, 3.0, 4.0, *d)
        out, col, _ = _column_per_cell_mesh(g, xs, k, (x, y, z), d, mesh.n_tets)
        assert out == ESCAPES
        cols[name] = np.empty_like(col)
        cols[name][order] = col
    assert np.count_nonzero(cols["identity"]) > 5
    np.testing.assert_allclose(cols["random"], cols["identity"], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(cols["morton"], cols["identity"], rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("p, d", [
    ((10.0, 10.0, -5.0), (0.0, 0.0, 1.0)),        # along mesh edges, through vertices
    ((0.0, 0.0, -5.0), (0.0, 0.0, 1.0)),          # along the boundary edge of the box
    ((-5.0, -5.0, -5.0), (1.0, 1.0, 1.0)),        # along the cube diagonals (Kuhn edges)
    ((-5.0, 10.0, 10.0), (1.0, 0.0, 0.0)),        # along edges in x
    ((-5.0, 15.0, 10.0), (1.0, 0.0, 0.0)),        # in a face plane
])
def test_adversarial_rays_cross_the_whole_box(xs, p, d):
    """Rays along edges, through vertices and in face planes of a voxel-like mesh: no loss."""
    mesh = box_mesh((3, 3, 3), (30.0, 30.0, 30.0))
    g = mesh_geometry(mesh, np.ones(mesh.n_points), np.zeros(mesh.n_tets, dtype=np.intp))
    d = np.array(d) / np.linalg.norm(d)
    k, x, y, z, n_reloc = enter_mesh(g, *p, *d)
    assert k >= 0 and n_reloc == 0
    out, col, counts = _column_per_cell_mesh(g, xs, k, (x, y, z), d, mesh.n_tets)
    chord = 30.0 * (np.sqrt(3.0) if d[0] * d[1] * d[2] else 1.0)
    assert out == ESCAPES and counts[:C_CROSSINGS].sum() == 0
    assert col.sum() == pytest.approx(chord, rel=1e-12)


def test_entry_from_outside_and_inside_matches_brute_force():
    mesh = box_mesh((3, 3, 3), (30.0, 30.0, 30.0), jitter=0.2, seed=3)
    rho = np.ones(mesh.n_points)
    g = mesh_geometry(mesh, rho, np.zeros(mesh.n_tets, dtype=np.intp))
    rng = np.random.default_rng(2)
    for _ in range(30):
        p = rng.uniform(-40.0, 70.0, 3)
        d = rng.uniform(5.0, 25.0, 3) - p
        d /= np.linalg.norm(d)
        ref = _reference_chords(mesh, rho, p, d)
        k, x, y, z, _ = enter_mesh(g, *p, *d)
        first = min(ref, key=lambda kk: ref[kk][0])
        assert k == first
        np.testing.assert_allclose((x, y, z), p + ref[first][0] * d, atol=1e-9)
    for _ in range(10):  # points inside: the kernel walks back from the boundary
        p = rng.uniform(1.0, 29.0, 3)
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        k, *_ = enter_mesh(g, *p, *d)
        ref = _reference_chords(mesh, rho, p, d)
        assert ref[k][0] == pytest.approx(0.0, abs=1e-9)


def test_ray_missing_the_mesh_reports_minus_one():
    mesh = box_mesh((2, 2, 2), (10.0, 10.0, 10.0))
    g = mesh_geometry(mesh, np.ones(mesh.n_points), np.zeros(mesh.n_tets, dtype=np.intp))
    assert enter_mesh(g, 20.0, 20.0, -5.0, 0.0, 0.0, 1.0)[0] == -1
    assert enter_mesh(g, 5.0, 5.0, -5.0, 0.0, 0.0, -1.0)[0] == -1


def test_exit_face_tie_goes_to_lowest_face_index():
    mesh = TetMesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]]),
                   np.array([[0, 1, 2, 3]]))
    g = mesh_geometry(mesh, np.ones(4), np.zeros(1, dtype=np.intp))
    d = np.array([1.0, 1.0, 1.0]) / np.sqrt(3)
    # from the origin vertex along the diagonal: only face 0 (x+y+z=1) lies ahead
    f, t = exit_face(g, 0, 0.0, 0.0, 0.0, *d, -1)
    assert f == 0 and t == pytest.approx(1 / np.sqrt(3))
    # through the edge x-axis: faces 2 (y = 0) and 3 (z = 0) tie; the lower index wins
    f, t = exit_face(g, 0, 0.1, 0.1, 0.1, 0.0, -1 / np.sqrt(2), -1 / np.sqrt(2), -1)
    assert f == 2 and t == pytest.approx(0.1 * np.sqrt(2))


def _reference_voxel_columns(lo, cell, n, rho, p, d):
    out = np.zeros(n[0] * n[1] * n[2])
    for i, j, k in itertools.product(range(n[0]), range(n[1]), range(n[2])):
        a = lo + np.array([i, j, k]) * cell
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (a - p) / d, (a + cell - p) / d
        t_in = np.nanmax(np.minimum(t1, t2))
        t_out = np.nanmin(np.maximum(t1, t2))
        vid = (k * n[1] + j) * n[0] + i
        out[vid] = max(t_out - max(t_in, 0.0), 0.0) * rho[vid]
    return out


def test_voxel_traversal_matches_brute_force(xs):
    grid = ImageGrid((0, 0, 0), (2.0, 3.0, 2.5), np.eye(3), (4, 3, 5))
    rng = np.random.default_rng(4)
    rho = rng.uniform(0.2, 2.0, grid.n_voxels)
    img = Image(rho.reshape(grid.shape), grid)
    lo, cell = -0.5 * grid.spacing_mm, grid.spacing_mm
    n = np.array(grid.size, dtype=np.intp)
    g = VoxelGeometry(lo, cell, n, img.array.reshape(-1).copy(), np.zeros(grid.n_voxels, np.intp))
    mu_en = transport_coefficients(xs, 0, 1.0)[1]
    for trial in range(30):
        p = rng.uniform(-10.0, 20.0, 3)
        d = rng.uniform(0.0, 8.0, 3) - p
        if trial < 4:  # axis-parallel rays (zero direction components)
            p, d = np.array([-3.0, 2.5 + 0.7 * trial, 0.75]), np.array([1.0, 0.0, 0.0])
        d /= np.linalg.norm(d)
        wg = voxel_world(g)
        vid, x, y, z, _ = start_cell(wg, *p, *d)  # no mesh: cell = voxel id, −1 if it misses
        ref = _reference_voxel_columns(lo, cell, n, rho, p, d)
        if vid < 0:
            assert ref.sum() == pytest.approx(0.0, abs=1e-9)
            continue
        tally = np.zeros(grid.n_voxels)
        out, *_ = flight_voxel(wg, xs, 1.0, vid, x, y, z, *d, 1e300, -1e-9, True,
                               tally, np.zeros(N_COUNTS, np.int64))
        assert out == ESCAPES
        np.testing.assert_allclose(tally * MM_PER_CM / mu_en, ref, atol=1e-9)


def test_entry_through_every_boundary_vertex_from_six_sides():
    """Rays aimed exactly at boundary vertices (on the faces' and the entry grid's planes) along
    ±x, ±y, ±z enter at that vertex: the entry grid lists every face in every cell it touches."""
    mesh = box_mesh((4, 4, 4), (40.0, 40.0, 40.0), origin_mm=(-20.0, -20.0, -20.0))
    g = mesh_geometry(mesh, np.ones(mesh.n_points), np.zeros(mesh.n_tets, dtype=np.intp))
    assert g.grid_n[0] > 1
    pts = mesh.points_mm
    for axis, sign in itertools.product(range(3), (1.0, -1.0)):
        d = np.zeros(3)
        d[axis] = sign
        face = pts[np.isclose(pts[:, axis], -20.0 * sign)]  # the side the rays enter through
        for v in face:
            k, x, y, z, _ = enter_mesh(g, *(v - 30.0 * d), *d)
            assert k >= 0
            np.testing.assert_allclose((x, y, z), v, atol=1e-9)


def test_prefetch_changes_no_value():
    """The prefetch intrinsic compiles for rows of 1-, 2- and 3-d arrays of several dtypes and
    leaves results untouched (it only hints the cache)."""
    from numba import njit

    from tetdose.transport.geometry._prefetch import prefetch

    @njit
    def prefetch_all_rows(a):
        for i in range(a.shape[0]):
            prefetch(a, i)
        return a.sum()

    @njit
    def plain_sum(a):
        return a.sum()

    rng = np.random.default_rng(0)
    for a in (rng.normal(size=17), rng.normal(size=(9, 4)), rng.normal(size=(5, 4, 4)),
              rng.integers(0, 9, size=(7, 4)).astype(np.int32)):
        before = a.copy()
        assert prefetch_all_rows(a) == plain_sum(a)
        np.testing.assert_array_equal(a, before)


def test_kernels_refuse_to_allocate():
    """``@kernel`` functions run without numba's reference counting, so an allocation inside one
    must fail at compile time rather than leak or crash at run time."""
    from numba.core.errors import NumbaError

    from tetdose._jit import kernel

    @kernel
    def borrows(a):
        return a[0] + a[-1]

    @kernel
    def allocates(n):
        return np.zeros(n).sum()

    assert borrows(np.arange(4.0)) == 3.0
    with pytest.raises(NumbaError):
        allocates(3)


def test_supporting_faces_of_a_box_and_of_a_u():
    """Every boundary face of a convex box supports the mesh; in a U the faces of the notch do
    not (a photon leaving through them can come back), the outer ones do."""
    from tetdose.transport.geometry._tet import SUPPORTING

    box = box_mesh((3, 1, 2), (120.0, 40.0, 80.0), origin_mm=(-60.0, -20.0, 0.0))
    g = mesh_geometry(box, np.ones(box.n_points), np.zeros(box.n_tets, dtype=np.intp))
    assert np.all((g.link >= 0) | (g.link == SUPPORTING))
    keep = np.ones(box.n_tets, bool)
    keep[6 * 4:6 * 4 + 6] = False  # cell (i=1, k=1): the notch
    u = TetMesh(box.points_mm, box.tets[keep])
    gu = mesh_geometry(u, np.ones(u.n_points), np.zeros(u.n_tets, dtype=np.intp))
    k, f = np.nonzero(gu.link < 0)
    normal_z = gu.planes[k, f, 2]
    notch_floor = (np.abs(normal_z - 1.0) < 1e-9) & np.isclose(gu.planes[k, f, 3], 40.0)
    assert notch_floor.any() and np.all(gu.link[k[notch_floor], f[notch_floor]] == -1)
    outer_bottom = (np.abs(normal_z + 1.0) < 1e-9)
    assert np.all(gu.link[k[outer_bottom], f[outer_bottom]] == SUPPORTING)


def test_every_voxel_a_boundary_triangle_crosses_lists_it():
    """Points sampled on every boundary triangle (a jittered mesh in a rotated grid) lie in
    voxels whose lists hold that triangle, and exactly the listed voxels are flagged."""
    from tetdose.transport.geometry.world import World, world_arrays

    c, s = np.cos(0.4), np.sin(0.4)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    grid = ImageGrid(rot @ [-45.0, -45.0, -10.0], np.array([3.0, 4.0, 5.0]), rot, (30, 25, 16))
    mesh = box_mesh((3, 3, 3), (30.0, 30.0, 30.0), origin_mm=(-15.0, -15.0, 0.0), jitter=0.25)
    mesh = mesh.with_data(point_data={"density": np.ones(mesh.n_points)})
    density = Image(np.ones(grid.shape), grid)
    arr = world_arrays(World(mesh=mesh, density=density),
                       lambda rho, region: (np.zeros(len(rho), np.intp), ["water"]))
    wg = arr.geometry
    rng = np.random.default_rng(3)
    tri = wg.tet.bnd_tri
    lo, cell, n = wg.vox.lo, wg.vox.cell, wg.vox.n
    for b in range(len(tri)):
        w = rng.dirichlet(np.ones(3), 40)
        pts = tri[b, 0] + w[:, 1:2] * tri[b, 1] + w[:, 2:3] * tri[b, 2]  # grid frame
        ijk = np.floor((pts - lo) / cell).astype(int)
        assert np.all((ijk >= 0) & (ijk < n))  # the mesh lies inside the grid
        for i, j, k in ijk:
            li, lj, lk = np.array([i, j, k]) - wg.tri_lo
            cidx = (lk * wg.tri_n[1] + lj) * wg.tri_n[0] + li
            assert b in wg.tri_items[wg.tri_start[cidx]:wg.tri_start[cidx + 1]]
            assert wg.vox.material[(k * n[1] + j) * n[0] + i] < 0  # flagged: −m − 1
    listed = np.diff(wg.tri_start) > 0
    assert (wg.vox.material < 0).sum() == listed.sum()


@pytest.fixture(scope="module")
def organ_mesh():
    """An unstructured mesh (the organ mesher's liver of the small phantom), in kernel order."""
    from tetdose.phantoms import make_phantom

    mesh = make_phantom("liver", seed=3, size="small", mesher="organ").mesh
    order = morton_order(mesh.centroids_mm)
    g = mesh_geometry(mesh, np.ones(mesh.n_points), np.zeros(mesh.n_tets, np.intp), order)
    return mesh, order, g


def _barycentric(mesh, k, p):
    v = mesh.points_mm[mesh.tets[k]]
    return np.linalg.solve(np.vstack([v.T, np.ones(4)]), np.append(p, 1.0))


def test_point_location_finds_the_tet_holding_each_point(organ_mesh):
    """Random points in the bounding box and near boundary faces (1e-3 mm in and out, ten times
    the tolerance that closes the float32 planes' slivers, LOCATE_TOL_MM): a located
    tet holds the point (barycentric coordinates ≥ 0), a point reported outside (−1) lies in no
    tet (brute force over every tet, numpy)."""
    mesh, order, g = organ_mesh
    rng = np.random.default_rng(11)
    lo, hi = mesh.points_mm.min(axis=0), mesh.points_mm.max(axis=0)
    pts = [rng.uniform(lo - 1.0, hi + 1.0, (1500, 3))]
    faces = mesh.boundary_faces[rng.integers(0, len(mesh.boundary_faces), 300)]
    tri = mesh.points_mm[faces]
    centre = tri.mean(axis=1)
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    for side in (-10 * LOCATE_TOL_MM, 10 * LOCATE_TOL_MM):
        pts.append(centre + side * normal)
    pts = np.concatenate(pts)
    v = mesh.points_mm[mesh.tets]  # (M, 4, 3)
    inv = np.linalg.inv(np.concatenate([v.transpose(0, 2, 1), np.ones((mesh.n_tets, 1, 4))],
                                       axis=1))
    found = {True: 0, False: 0}
    for p in pts:
        k = locate_point(g, *p)
        if k >= 0:
            assert _barycentric(mesh, order[k], p).min() > -1e-9
        else:
            bary = inv @ np.append(p, 1.0)
            assert np.all(bary.min(axis=1) < 1e-12), p
        found[k >= 0] += 1
    assert min(found.values()) > 300  # both kinds of point were tested


def test_point_location_grid_lists_every_tet_that_meets_a_cell(organ_mesh):
    """Each tet is listed in the cell of each of its vertices, of its centroid and of random
    points inside it (the cells its points fall in)."""
    mesh, order, g = organ_mesh
    rng = np.random.default_rng(12)
    pts = mesh.points_mm[mesh.tets[order]]  # kernel order
    bary = rng.dirichlet(np.ones(4), (len(pts), 3))
    inside = np.einsum("mnv,mva->mna", bary, pts)
    for p in (pts, inside, pts.mean(axis=1, keepdims=True)):
        idx = np.floor((p - g.loc_lo) / g.loc_cell).astype(int)
        assert np.all((idx >= 0) & (idx < g.loc_n))
        cell = (idx[..., 2] * g.loc_n[1] + idx[..., 1]) * g.loc_n[0] + idx[..., 0]
        for k in range(len(pts)):
            for c in cell[k]:
                assert k in g.loc_items[g.loc_start[c]:g.loc_start[c + 1]]
