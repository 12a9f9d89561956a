"""Tests for handanno_core.flow: dense SIFT, SIFT Flow, DIS flow, NCC matching, flow sampling."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from handanno_core.flow import (
    coarse_to_fine,
    dense_sift,
    dis_flow,
    ncc_match,
    sample_flow,
    sift_flow,
)


def hand_like_crop(size: int = 128, seed: int = 0) -> np.ndarray:
    """A normalized depth crop with a palm, five fingers and surface relief (background +1)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32)
    c = size / 2
    img = np.ones((size, size), np.float32)
    palm = ((xx - c) / 28) ** 2 + ((yy - c - 10) / 24) ** 2
    img = np.minimum(img, np.where(palm < 1, -0.2 + 0.3 * palm, 1.0))
    for k in range(5):
        ang = np.deg2rad(-60 + 30 * k + rng.normal(0, 5))
        length = 45 + rng.normal(0, 5)
        x0, y0 = c + 20 * np.sin(ang), c - 10 - 20 * np.cos(ang)
        dx, dy = np.sin(ang), -np.cos(ang)
        t = np.clip((xx - x0) * dx + (yy - y0) * dy, 0, length)
        dist = np.hypot(xx - (x0 + t * dx), yy - (y0 + t * dy))
        finger = -0.3 - 0.04 * k + 0.01 * t + 0.5 * (dist / 6) ** 2
        img = np.minimum(img, np.where(dist < 6, finger, 1.0))
    # knuckle-like relief: smooth random bumps on the hand only
    bumps = cv2.GaussianBlur(rng.normal(0, 1, (size, size)).astype(np.float32), (0, 0), 3) * 0.6
    hand = img < 1.0
    img[hand] = np.clip(img[hand] + bumps[hand], -1, 0.99)
    return img


def affine_pair(img: np.ndarray, deg: float, shift: tuple[float, float], scale: float = 1.0):
    """``moving`` with ``moving(A x + b) = img(x)`` and the exact flow ``A x + b - x``."""
    h, w = img.shape
    c = np.array([w / 2 - 0.5, h / 2 - 0.5])
    th = np.deg2rad(deg)
    a = scale * np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    b = c + np.asarray(shift) - a @ c
    m = np.hstack([a, b[:, None]])
    moving = cv2.warpAffine(img, m, (w, h), flags=cv2.INTER_LINEAR, borderValue=1.0)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    fx = a[0, 0] * xx + a[0, 1] * yy + b[0] - xx
    fy = a[1, 0] * xx + a[1, 1] * yy + b[1] - yy
    return moving.astype(np.float32), np.stack([fx, fy], -1)


def hand_epe(ref: np.ndarray, flow: np.ndarray, truth: np.ndarray) -> float:
    mask = cv2.erode((ref < 0.99).astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    return float(np.mean(np.linalg.norm(flow - truth, axis=-1)[mask]))


CASES = [
    pytest.param(0.0, (3.4, -2.3), 1.0, id="shift"),
    pytest.param(5.0, (1.5, -2.0), 1.03, id="warp"),
]


@pytest.mark.parametrize(("deg", "shift", "scale"), CASES)
def test_dis_flow_recovers_shift_and_warp(deg, shift, scale):
    ref = hand_like_crop()
    moving, truth = affine_pair(ref, deg, shift, scale)
    flow = dis_flow(ref, moving)
    assert flow.shape == (128, 128, 2) and flow.dtype == np.float32
    assert hand_epe(ref, flow, truth) < 0.5


@pytest.mark.parametrize(
    ("deg", "shift", "scale", "limit"),
    [(0.0, (3.4, -2.3), 1.0, 0.5), (5.0, (1.5, -2.0), 1.03, 0.75)],
)
def test_sift_flow_recovers_shift_and_warp(deg, shift, scale, limit):
    """At the paper's setting (full resolution, 3 levels). The discrete labels plus a sub-pixel
    fit reach 0.35 px on the shift; the rotated+scaled warp stays ~0.55 px (edge pixels)."""
    ref = hand_like_crop()
    moving, truth = affine_pair(ref, deg, shift, scale)
    flow = sift_flow(ref, moving, working_size=None, levels=3)
    assert flow.shape == (128, 128, 2)
    assert hand_epe(ref, flow, truth) < limit


def test_sift_flow_default_working_resolution():
    ref = hand_like_crop()
    moving, truth = affine_pair(ref, 0.0, (3.4, -2.3))
    flow = sift_flow(ref, moving)  # matched at 64x64, upsampled
    assert flow.shape == (128, 128, 2)
    assert hand_epe(ref, flow, truth) < 0.7


def test_sift_flow_zero_for_identical_images():
    ref = hand_like_crop(seed=3)
    flow = sift_flow(ref, ref)
    hand = cv2.erode((ref < 0.99).astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    assert np.abs(flow[hand]).max() < 0.4  # sub-pixel fit near the silhouette
    assert np.median(np.abs(flow[hand])) < 0.1
    assert np.abs(np.median(flow, axis=(0, 1))).max() < 1e-6


def test_dense_sift_shape_norm_and_shift_equivariance():
    img = hand_like_crop(64, seed=1)
    d = dense_sift(img)
    assert d.shape == (64, 64, 128) and d.dtype == np.float32
    norms = np.linalg.norm(d, axis=-1)
    textured = norms > 0.5
    assert textured.mean() > 0.2
    np.testing.assert_allclose(norms[textured], 1.0, atol=1e-4)
    shifted = np.roll(img, (3, 5), axis=(0, 1))
    ds = dense_sift(shifted)
    # away from the wrap-around border the descriptors move with the image
    np.testing.assert_allclose(ds[15:50, 15:50], d[12:47, 10:45], atol=1e-4)
    d8 = dense_sift(img, as_uint8=True)
    assert d8.dtype == np.uint8 and d8.shape == (64, 64, 128)


def test_ncc_match_finds_shifted_patches():
    ref = hand_like_crop(seed=2)
    moving, truth = affine_pair(ref, 0.0, (2.6, 1.7))
    pts = np.array([[64.0, 60.0], [50.0, 45.0], [75.0, 70.0]])
    disp, score = ncc_match(ref, moving, pts)
    expected = truth[pts[:, 1].astype(int), pts[:, 0].astype(int)]
    np.testing.assert_allclose(disp, expected, atol=0.5)
    assert np.all(score > 0.9)
    # a NaN point gives NaN, not an exception
    disp, _ = ncc_match(ref, moving, np.array([[np.nan, 1.0]]))
    assert np.all(np.isnan(disp))


def test_sample_flow_bilinear_median():
    yy, xx = np.mgrid[0:32, 0:32].astype(np.float32)
    flow = np.stack(
        [xx * 0.5, yy * 0.25], -1
    )  # linear field: median of a symmetric window = centre
    pts = np.array([[10.25, 12.5], [3.0, 4.0], [np.nan, 2.0]])
    out = sample_flow(flow, pts, radius=1)
    np.testing.assert_allclose(out[:2], [[5.125, 3.125], [1.5, 1.0]], atol=1e-5)
    assert np.all(np.isnan(out[2]))


def test_coarse_to_fine_visits_levels_coarse_first():
    seen = []

    def solver(a, b, init, level):
        seen.append((level, a.shape[:2], float(np.abs(init).max())))
        return init + 1.0

    out = coarse_to_fine(np.zeros((64, 64)), np.zeros((64, 64)), solver, levels=3)
    assert [s[0] for s in seen] == [2, 1, 0]
    assert [s[1] for s in seen] == [(16, 16), (32, 32), (64, 64)]
    # flow from a coarser level is upsampled and scaled by 2: 1 -> 2 (+1) -> 6 (+1) = 7
    assert seen[1][2] == pytest.approx(2.0) and seen[2][2] == pytest.approx(6.0)
    assert out.shape == (64, 64, 2) and np.allclose(out, 7.0)
