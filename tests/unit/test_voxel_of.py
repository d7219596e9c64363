"""ImageGrid.voxel_of: the one point → voxel rule, i = ⌊x + ½⌋ (a face point goes up)."""

import numpy as np

from tetdose.core.image import ImageGrid


def test_face_points_go_to_the_upper_voxel_and_outer_faces_follow_the_rule():
    grid = ImageGrid((0.0, 0.0, 0.0), (2.0, 2.0, 2.0), np.eye(3), (3, 3, 3))
    # continuous index x = 0.5, 1.5 (faces inside), −0.5 (lower outer face), 2.5 (upper outer)
    pts = np.array([[1.0, 0.0, 0.0], [3.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [5.0, 0.0, 0.0],
                    [0.0, 0.0, 3.0]])
    # rint would give 0 and 2 for the first two (halves to even) and 2 for the fifth's z
    np.testing.assert_array_equal(grid.voxel_of(pts), [1, 2, 0, -1, 2 * 9])


def test_voxel_of_is_the_nearest_centre_on_a_rotated_grid():
    """Independent reference: the voxel whose centre is nearest in the grid frame (per axis)."""
    c, s = np.cos(0.3), np.sin(0.3)
    direction = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    grid = ImageGrid((5.0, -3.0, 2.0), (1.5, 2.0, 2.5), direction, (4, 5, 6))
    rng = np.random.default_rng(7)
    pts = grid.index_to_physical(rng.uniform(-1.5, 6.5, size=(2000, 3)))
    got = grid.voxel_of(pts)
    centres = grid.voxel_centers_mm()
    q_pts, q_cen = grid.to_grid_frame(pts), grid.to_grid_frame(centres)
    inside = np.all((q_pts >= grid.bounds_grid_frame()[0])
                    & (q_pts < grid.bounds_grid_frame()[1]), axis=1)
    np.testing.assert_array_equal(got < 0, ~inside)
    per_axis = np.abs(q_pts[inside] - q_cen[got[inside]])
    assert np.all(per_axis <= 0.5 * grid.spacing_mm + 1e-9)
