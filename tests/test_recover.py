"""Tests of handanno_core.recover: frames the hand model cannot explain are fitted again from their
well-explained neighbours and per-finger hypotheses (flexion and abduction), and replaced only
where the model explains them far better; depth rendered from the capsule model itself."""

from __future__ import annotations

import numpy as np
import pytest
from test_handmodel import CAM, _model, _noisy_crop, _pose, _render, _rot

from handanno_core import handmodel as hm
from handanno_core.crops import crop_boxes
from handanno_core.recover import RecoverySettings, _nearest_good, carry_unseen, recover_frames
from handanno_core.skeleton import MSRA21


def _subtree(k: int) -> list[int]:
    par = MSRA21.parent_array
    sub = [k]
    for q in MSRA21.topological_order:
        if par[q] in sub:
            sub.append(int(q))
    return sub


def _slide_finger(x: np.ndarray, mcp: int, deg: float) -> np.ndarray:
    """``x`` with the finger below joint ``mcp`` turned by ``deg`` about the palm normal at its
    knuckle (abduction: the finger slides sideways, onto its neighbour)."""
    out = x.copy()
    sub = _subtree(mcp)[1:]
    out[sub] = (out[sub] - out[mcp]) @ _rot(MSRA21.palm_normal(x), deg).T + out[mcp]
    return out


def _spin(x: np.ndarray, deg: float) -> np.ndarray:
    """``x`` turned by ``deg`` about the viewing direction through its centroid."""
    c = x.mean(axis=0)
    return (x - c) @ _rot(np.array([0.0, 0.0, 1.0]), deg).T + c


@pytest.fixture(scope="module")
def scene():
    """Five frames of one open hand moving 4 mm per frame (2 mm sensor noise), their model and
    observations."""
    rng = np.random.default_rng(0)
    x0 = _pose("open")
    poses = [x0 + [4.0 * i, 0.0, 0.0] for i in range(5)]
    model = _model(x0)
    centres = np.stack([p.mean(axis=0) for p in poses])
    crops = np.stack(
        [_noisy_crop(_render(model, p), c, rng) for p, c in zip(poses, centres, strict=True)]
    )
    obs = hm.observe(crops, crop_boxes(centres, CAM), centres, CAM)
    level = hm.reference_level(model, np.stack(poses)[[0, 4]], obs.take([0, 4]), CAM)
    return np.stack(poses), model, obs, centres, level


def test_a_hand_in_the_wrong_basin_is_refitted_from_its_neighbours(scene):
    """Frame 2 is turned 70 degrees about the viewing axis (its fingers on the wrong surface):
    started from its neighbours' estimates it comes back to the rendered pose (within the 2 mm sensor noise); every other frame,
    already explained, and the references (kept) are returned unchanged."""
    truth, model, obs, centres, level = scene
    est = truth.copy()
    est[2] = _spin(truth[2], 70.0)
    keep = np.array([True, False, False, False, True])
    res = recover_frames(model, est, obs, centres, CAM, level, keep=keep)
    assert list(res.tried) == [2]
    assert list(res.recovered) == [2]
    assert res.level_before[2] > 3.0 * res.level_after[2]
    err = np.linalg.norm(res.joints_mm[2] - truth[2], axis=1)
    assert err.max() <= 5.0 and err.mean() <= 2.0, np.round(err, 1)
    others = [0, 1, 3, 4]
    assert np.array_equal(res.joints_mm[others], est[others])


def test_a_finger_slid_onto_its_neighbour_comes_back_by_the_abduction_hypotheses(scene):
    """The middle finger turned 20 degrees onto the ring finger, with no neighbour to start
    from: the plain fit leaves it there (its tip > 10 mm off); the abduction hypotheses bring
    every joint back to within 5 mm."""
    truth, model, obs, centres, level = scene
    x = truth[2]
    wrong = _slide_finger(x, MSRA21.joint_names.index("middle_mcp"), 20.0)
    kin = hm.Kinematics(MSRA21, model.bone_lengths_mm)
    pri = hm.Priors(pose=wrong[None], pose_w=np.ones((1, len(x))))
    plain = hm.fit_frames(model, wrong[None], obs.take([2]), CAM, priors=pri, kin=kin)
    stuck = np.linalg.norm(plain.joints_mm[0] - x, axis=1)
    assert stuck.max() > 10.0, np.round(stuck, 1)
    res = recover_frames(
        model, wrong[None], obs.take([2]), centres[[2]], CAM, level,
        settings=RecoverySettings(neighbours=0),
    )  # fmt: skip
    assert list(res.recovered) == [0]
    err = np.linalg.norm(res.joints_mm[0] - x, axis=1)
    assert err.max() <= 5.0 and err.mean() <= 2.0, np.round(err, 1)


def test_a_fit_the_model_explains_only_somewhat_better_is_not_kept(scene):
    """The acceptance rule: a new fit must explain the depth ``min_gain`` times better; with an
    unreachable gain nothing is replaced, and the levels before and after are equal."""
    truth, model, obs, centres, level = scene
    est = truth.copy()
    est[2] = _spin(truth[2], 70.0)
    res = recover_frames(
        model, est, obs, centres, CAM, level, settings=RecoverySettings(min_gain=1e6)
    )
    assert len(res.recovered) == 0 and list(res.tried) == [2]
    assert np.array_equal(res.joints_mm, est)
    assert np.array_equal(res.level_after, res.level_before)


def test_a_hand_without_a_neighbour_in_its_basin_is_refitted_from_the_references(scene):
    """Frame 2 turned 70 degrees and no neighbour taken as a start (``neighbours=0``: a hand that
    jumped, whose neighbours are wrong too): its own start and the finger hypotheses leave it
    there; the references' poses as starts (``reference_starts``) bring it back."""
    truth, model, obs, centres, level = scene
    est = truth.copy()
    est[2] = _spin(truth[2], 70.0)
    keep = np.array([True, False, False, False, True])
    alone = RecoverySettings(neighbours=0, reference_starts=0)
    res = recover_frames(model, est, obs, centres, CAM, level, keep=keep, settings=alone)
    assert list(res.tried) == [2] and len(res.recovered) == 0
    refs = RecoverySettings(neighbours=0, reference_starts=1)
    res = recover_frames(model, est, obs, centres, CAM, level, keep=keep, settings=refs)
    assert list(res.recovered) == [2]
    err = np.linalg.norm(res.joints_mm[2] - truth[2], axis=1)
    assert err.max() <= 5.0 and err.mean() <= 2.0, np.round(err, 1)


def _local_bones(x: np.ndarray) -> np.ndarray:
    """(J, 3): each joint relative to its parent in the palm's frame (the root's row is 0)."""
    par = MSRA21.parent_array
    rel = np.where((par >= 0)[:, None], x - x[np.maximum(par, 0)], 0.0)
    return rel @ MSRA21.palm_rotation(x)


def test_carried_joints_keep_their_old_articulation_on_the_new_palm():
    old = _pose("open")
    fist = _pose("fist", ypr=(20.0, -10.0, 35.0), centre=(15.0, -8.0, 430.0))
    unseen = np.zeros(21, dtype=bool)
    unseen[[18, 7]] = True  # the thumb's MCP and the middle finger's DIP
    out = carry_unseen(MSRA21, old, fist, unseen)
    carried = [18, 19, 20, 7, 8]  # and every joint below them
    rest = np.setdiff1d(np.arange(21), carried)
    assert np.array_equal(out[rest], fist[rest])
    np.testing.assert_allclose(_local_bones(out)[carried], _local_bones(old)[carried], atol=1e-9)
    np.testing.assert_allclose(MSRA21.bone_lengths(out), MSRA21.bone_lengths(fist), atol=1e-9)
    assert np.linalg.norm(out[20] - fist[20]) > 20.0  # the open thumb, not the fist's
    # the whole hand moved rigidly: its articulation is the old one everywhere, nothing changes
    moved = _spin(old, 50.0) + [5.0, 0.0, 20.0]
    np.testing.assert_allclose(carry_unseen(MSRA21, old, moved, unseen), moved, atol=1e-9)
    assert carry_unseen(MSRA21, old, fist, np.zeros(21, dtype=bool)) is fist


def test_a_recovered_hand_carries_what_lies_past_the_images_border(scene):
    """A sensor whose image ends across the thumb (no depth past row 125): frame 2 turned 70
    degrees, its estimated thumb past the border. Recovery turns the hand back from its
    neighbours; the thumb, which no depth shows, keeps the estimate's articulation and comes
    back with the palm instead of being placed by a fit that cannot see it."""
    truth, model, _, centres, level = scene
    rng = np.random.default_rng(1)
    border = 125
    cam = CAM.model_copy(update={"height": border})
    crops = []
    for p, c in zip(truth, centres, strict=True):
        depth = _render(model, p)
        depth[border:] = 0.0
        crops.append(_noisy_crop(depth, c, rng))
    obs = hm.observe(np.stack(crops), crop_boxes(centres, CAM), centres, CAM)
    est = truth.copy()
    est[2] = _spin(truth[2], 70.0)
    off = ~cam.on_image(cam.project(est[2]))
    assert list(np.flatnonzero(off)) == [19, 20]
    keep = np.array([True, False, False, False, True])
    res = recover_frames(model, est, obs, centres, cam, level, keep=keep)
    assert list(res.recovered) == [2]
    err = np.linalg.norm(res.joints_mm[2] - truth[2], axis=1)
    seen = ~off & cam.on_image(cam.project(truth[2]))  # the depth shows it at both poses
    assert err[seen].max() <= 5.0, np.round(err, 1)
    np.testing.assert_allclose(
        _local_bones(res.joints_mm[2])[off], _local_bones(est[2])[off], atol=1e-6
    )
    assert err[off].max() <= 8.0, np.round(err, 1)  # spun rigidly: the old thumb was right


def test_neighbours_are_taken_within_the_frames_segment_only():
    good = np.array([0, 1, 2, 6, 7, 9])
    seg = np.array([0, 0, 0, 0, 0, 1, 1, 1, 1, 1])  # a break at frame 5
    assert _nearest_good(4, good, seg, 2) == (1, 2)
    assert _nearest_good(5, good, seg, 2) == (6, 7)
    assert _nearest_good(8, good, seg, 1) == (7, 9)
    assert _nearest_good(6, good, seg, 1) == (7,)  # a frame is not its own neighbour


def test_finger_grid_sets_each_first_joints_abduction():
    flex, abd = hm.finger_grid(MSRA21, abductions=(0.0, 1.0))
    g = hm.grid_flexions(MSRA21)
    assert flex.shape == abd.shape == (2 * len(g), len(MSRA21.angle_joints))
    assert np.allclose(flex[: len(g)], g) and np.allclose(flex[len(g) :], g)
    _, lim = MSRA21.angle_limits()
    first = [int(c[0]) for c in hm.finger_chains(MSRA21)]
    assert np.allclose(abd[: len(g), first], lim[first, 0])
    assert np.allclose(abd[len(g) :, first], lim[first, 1])
    rest = np.setdiff1d(np.arange(len(MSRA21.angle_joints)), first)
    assert np.all(np.isnan(abd[:, rest]))
