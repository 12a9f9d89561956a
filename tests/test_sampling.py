"""The one depth lookup, visibility rule and bilinear sampler (handanno_core.sampling)."""

import numpy as np

from handanno_core.camera import CameraIntrinsics
from handanno_core.sampling import (
    VISIBILITY_MARGIN_MM,
    bilinear,
    bilinear_gradient,
    depth_at,
    visible_by_depth,
)

CAM = CameraIntrinsics(fx=100.0, fy=100.0, cx=20.0, cy=15.0, width=40, height=30)


def test_depth_at_closest_in_block_then_nearest_valid():
    d = np.zeros((30, 40))
    d[10, 10] = 500.0
    d[10, 11] = 450.0  # inside the 3x3 block of (10, 10): the closer surface wins
    d[20, 25] = 700.0  # 3 px from (22, 20): found only through the window
    got = depth_at(d, np.array([[10.2, 9.8], [22.0, 20.0], [35.0, 5.0], [np.nan, 1.0]]))
    np.testing.assert_array_equal(got[:2], [450.0, 700.0])
    assert np.isnan(got[2]) and np.isnan(got[3])
    # near_px=0: the nearest valid pixel, no block
    assert depth_at(d, np.array([[10.0, 10.0]]), window=3, near_px=0)[0] == 500.0


def test_visible_by_depth_occluder_dropout_and_off_image():
    x = np.array([[0.0, 0.0, 400.0], [0.0, 0.0, 400.0], [0.0, 0.0, 400.0], [1000.0, 0.0, 400.0]])
    uv = np.rint(CAM.project(x)).astype(int)
    offsets = np.full(4, 8.0)
    surface = np.full((30, 40), 400.0 - 8.0)
    assert visible_by_depth(x, surface, CAM, offsets).tolist() == [True, True, True, False]
    # an occluder in the 3x3 block more than the margin in front -> hidden
    occluded = surface.copy()
    occluded[uv[0, 1] + 1, uv[0, 0] - 1] = 400.0 - 8.0 - VISIBILITY_MARGIN_MM - 1.0
    assert not visible_by_depth(x[:1], occluded, CAM, offsets[:1])[0]
    # within the margin -> still visible
    occluded[uv[0, 1] + 1, uv[0, 0] - 1] = 400.0 - 8.0 - VISIBILITY_MARGIN_MM + 1.0
    assert visible_by_depth(x[:1], occluded, CAM, offsets[:1])[0]
    # dropout at the centre pixel only: the 3x3 block still sees the surface
    hole = surface.copy()
    hole[uv[0, 1], uv[0, 0]] = 0.0
    assert visible_by_depth(x[:1], hole, CAM, offsets[:1])[0]
    # no valid depth in the block -> not visible
    hole[uv[0, 1] - 1 : uv[0, 1] + 2, uv[0, 0] - 1 : uv[0, 0] + 2] = 0.0
    assert not visible_by_depth(x[:1], hole, CAM, offsets[:1])[0]
    assert not visible_by_depth(np.full((1, 3), np.nan), surface, CAM)[0]


def test_bilinear_exact_on_planes_and_gradient():
    yy, xx = np.mgrid[0:12, 0:16].astype(np.float64)
    plane = 3.0 * xx - 2.0 * yy + 5.0
    rng = np.random.default_rng(1)
    x, y = rng.uniform(0, 15, 200), rng.uniform(0, 11, 200)
    np.testing.assert_allclose(bilinear(plane, x, y), 3.0 * x - 2.0 * y + 5.0, atol=1e-9)
    s = bilinear_gradient(plane, x, y)
    np.testing.assert_allclose(s.dx, 3.0, atol=1e-9)
    np.testing.assert_allclose(s.dy, -2.0, atol=1e-9)
    # off the image: the border is replicated
    np.testing.assert_allclose(
        bilinear(plane, np.array([-4.0, 40.0]), np.array([0.0, 0.0])), [5, 50]
    )


def test_bilinear_on_a_stack_reads_the_given_frame():
    rng = np.random.default_rng(2)
    stack = rng.random((3, 10, 10)).astype(np.float16)
    x, y = rng.uniform(0, 9, (3, 5)), rng.uniform(0, 9, (3, 5))
    frames = np.arange(3)[:, None]
    got = bilinear_gradient(stack, x, y, frame=frames, dtype=np.float32)
    for f in range(3):
        one = bilinear(stack[f], x[f], y[f], dtype=np.float32)
        np.testing.assert_array_equal(got.value[f], one)
        assert np.all(got.lo[f] <= got.value[f] + 1e-6) and np.all(got.value[f] <= got.hi[f] + 1e-6)
