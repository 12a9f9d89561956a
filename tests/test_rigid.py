"""handanno_core.rigid.kabsch: the rigid motion between two point sets."""

from __future__ import annotations

import numpy as np

from handanno_core.rigid import kabsch


def _rotation(axis: np.ndarray, degrees: float) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    a = np.radians(degrees)
    return np.eye(3) + np.sin(a) * k + (1 - np.cos(a)) * k @ k


def test_a_known_motion_is_recovered_from_noisy_points():
    rng = np.random.default_rng(0)
    a = rng.normal(0.0, 40.0, (12, 3))
    rot = _rotation(np.array([1.0, 2.0, -0.5]), 70.0)
    b = a @ rot.T + np.array([10.0, -30.0, 400.0]) + rng.normal(0.0, 0.2, a.shape)
    fit_rot, ca, cb = kabsch(a, b)
    np.testing.assert_allclose(fit_rot, rot, atol=5e-3)
    moved = (a - ca) @ fit_rot.T + cb
    assert np.abs(moved - b).max() < 1.0
    assert np.linalg.det(fit_rot) > 0.999  # a rotation, never a mirror


def test_a_mirrored_set_gets_a_proper_rotation():
    rng = np.random.default_rng(1)
    a = rng.normal(0.0, 40.0, (8, 3))
    fit_rot, _, _ = kabsch(a, a * np.array([-1.0, 1.0, 1.0]))
    assert np.linalg.det(fit_rot) > 0.999


def test_points_that_fix_no_rotation_give_none():
    line = np.outer(np.arange(5.0), [1.0, 2.0, 3.0])
    assert kabsch(line, line + 5.0) is None  # collinear: any turn about the line fits
    assert kabsch(line[:2], line[:2]) is None  # fewer than 3 points
