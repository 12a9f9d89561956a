"""benchmarks/bench_hidden_bound.py: finger shapes taken off one palm and put on another."""

from __future__ import annotations

import numpy as np
from benchmark_scripts import load_benchmark

from handanno_core.skeleton import MSRA21
from handanno_core.synth import rotation_matrices


def _bound_module():
    return load_benchmark("bench_hidden_bound")


def _poses(n: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).normal(scale=40.0, size=(n, MSRA21.num_joints, 3))


def test_a_poses_own_finger_shapes_on_its_own_palm_give_the_pose_back():
    hb = _bound_module()
    x = _poses(5)
    back = hb.place_shapes(MSRA21, hb.finger_shapes(MSRA21, x), x)
    np.testing.assert_allclose(back, x, atol=1e-9)


def test_finger_shapes_move_with_the_palm_they_are_put_on():
    hb = _bound_module()
    x = _poses(1, seed=1)[0]
    r = rotation_matrices(np.array([[20.0, -65.0, 40.0]]))[0]
    moved = x @ r.T + np.array([20.0, -5.0, 400.0])
    # x's finger shapes on the moved palm: the moved pose itself
    np.testing.assert_allclose(
        hb.place_shapes(MSRA21, hb.finger_shapes(MSRA21, x), moved), moved, atol=1e-9
    )
    # another pose's finger shapes keep the palm's joints (root and finger bases) where they are
    other = hb.place_shapes(MSRA21, hb.finger_shapes(MSRA21, _poses(1, seed=2)[0]), moved)
    bases = np.unique(MSRA21.finger_bases)
    np.testing.assert_allclose(other[bases], moved[bases], atol=1e-9)
    assert not np.allclose(other, moved)


def test_shapes_interpolate_in_time_between_the_anchors_of_the_frames_segment():
    hb = _bound_module()
    n = 18
    values = np.zeros((n, 2, 3))
    anchors = np.zeros((n, 2), dtype=bool)
    for f, v in ((2, 0.0), (6, 10.0), (12, 50.0)):  # joint 0's anchors
        values[f, 0], anchors[f, 0] = v, True
    values[4, 1], anchors[4, 1] = 7.0, True  # joint 1: one anchor
    segment = np.array([0] * 10 + [1] * 5 + [2] * 3)  # breaks at frames 10 and 15
    lin = hb.interpolate_at_anchors(values, anchors, segment)[..., 0]
    near = hb.interpolate_at_anchors(values, anchors, segment, nearest=True)[..., 0]
    assert lin[0, 0] == 0.0 and near[0, 0] == 0.0  # before the first anchor: its value
    assert lin[3, 0] == 2.5 and near[3, 0] == 0.0  # a quarter of the way from frame 2 to 6
    assert lin[5, 0] == 7.5 and near[5, 0] == 10.0
    assert lin[6, 0] == 10.0  # an anchor keeps its value
    assert lin[9, 0] == 10.0  # after 6 in its segment: the anchor at 12 lies past the break
    assert lin[13, 0] == 50.0  # the second segment's only anchor
    assert np.isnan(lin[16, 0]) and np.isnan(near[16, 0])  # a segment with no anchor
    assert np.all(lin[:10, 1] == 7.0) and np.isnan(lin[10:, 1]).all()  # each joint its own
