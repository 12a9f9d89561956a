"""Tests of the per-finger hypotheses of the hand-model fit (handmodel.refit_fingers): a finger
started in the wrong flexion basin stays there under the plain fit and is recovered by trying
each finger curled and extended; depth rendered from the capsule model itself."""

from __future__ import annotations

import numpy as np
import pytest
from test_handmodel import CAM, _model, _observe, _pose, _rot

from handanno_core import handmodel as hm
from handanno_core.crops import crop_boxes, crop_depth
from handanno_core.skeleton import MSRA21
from handanno_core.synth import Primitives, render_depth


@pytest.fixture(scope="module")
def scene():
    x = _pose("open")
    model = _model(x)
    return x, model, _observe(model, [x])


def _flex_finger(x: np.ndarray, finger: int, deg: float) -> np.ndarray:
    """``x`` with finger ``finger`` (:func:`hm.finger_chains`) turned by ``deg/2`` at each of its
    first two angle joints (MCP and PIP) about their flexion axes (``deg`` in all)."""
    sk = MSRA21
    par = sk.parent_array
    out = x.copy()
    normal = sk.palm_normal(x)
    for pos in hm.finger_chains(sk)[finger][:2]:
        k = int(sk.angle_joints[pos])
        lateral = np.cross(out[k] - out[par[k]], normal)
        sub = [int(sk.children(k)[0])]
        for q in sk.topological_order:
            if par[q] in sub:
                sub.append(int(q))
        out[sub] = (out[sub] - out[k]) @ _rot(lateral, deg / 2).T + out[k]
    return out


def test_finger_chains_are_the_five_fingers_proximal_first():
    chains = hm.finger_chains(MSRA21)
    assert len(chains) == 5
    aj = MSRA21.angle_joints
    for c in chains:
        assert len(c) == 3
        # each angle joint's parent is the previous one: a chain from the palm outwards
        assert np.all(MSRA21.parent_array[aj[c[1:]]] == aj[c[:-1]])
        assert MSRA21.parent_array[aj[c[0]]] == MSRA21.root


def test_finger_hypotheses_set_the_requested_flexion(scene):
    x, model, _ = scene
    kin = hm.Kinematics(MSRA21, model.bone_lengths_mm)
    root, u = kin.fit(x[None])
    targets = hm.grid_flexions(MSRA21)  # (K, A)
    hyp = hm.finger_hypotheses(MSRA21, kin, root, u, targets)  # (1, F, K, B, 3)
    chains = hm.finger_chains(MSRA21)
    assert hyp.shape == (1, len(chains), len(targets), len(MSRA21.bones), 3)
    flex0, abd0 = MSRA21.joint_angles(x)
    for f, chain in enumerate(chains):
        xs = kin.joints(np.repeat(root, len(targets), 0), hyp[0, f])
        flex, abd = MSRA21.joint_angles(xs)
        assert np.allclose(flex[:, chain], targets[:, chain], atol=1.0)
        others = np.setdiff1d(np.arange(len(flex0)), chain)
        assert np.allclose(flex[:, others], flex0[others], atol=1e-6)
        assert np.allclose(abd[:, chain[0]], abd0[chain[0]], atol=2.0)
        assert np.allclose(MSRA21.bone_lengths(xs), model.bone_lengths_mm, atol=1e-6)


@pytest.mark.parametrize("finger,deg", [(2, 90.0), (0, 75.0), (1, -60.0)])
def test_hypotheses_recover_a_finger_the_plain_fit_leaves_stuck(scene, finger, deg):
    """One finger flexed 60-90 degrees away from the rendered pose: the plain fit stays stuck
    (its tip > 15 mm off); with the per-finger hypotheses every joint comes back to <= 2 mm.
    (Since stop 49 the fit leaves the points less than 25 mm past the wrist to the arm, and with
    a full-weight prior to the start the ring and index fingers flexed 60 degrees end 6-13 mm off
    in the plain fit, where no hypothesis is lower: this scene has no arm. HISTORY.md, stop 49.)"""
    x, model, obs = scene
    start = _flex_finger(x, finger, deg)
    pri = hm.Priors(pose=start[None], pose_w=np.ones((1, len(x))))
    kin = hm.Kinematics(MSRA21, model.bone_lengths_mm)
    fit = hm.fit_frames(model, start[None], obs, CAM, priors=pri, kin=kin)
    stuck = np.linalg.norm(fit.joints_mm[0] - x, axis=1)
    assert stuck.max() > 15.0, np.round(stuck, 1)
    out = hm.refit_fingers(model, fit, obs, CAM, priors=pri, kin=kin)
    err = np.linalg.norm(out.joints_mm[0] - x, axis=1)
    assert err.max() <= 2.0, np.round(err, 2)
    assert out.energy[0] < fit.energy[0]


def test_frames_not_tried_or_not_improved_keep_their_fit_exactly(scene):
    x, model, obs = scene
    kin = hm.Kinematics(MSRA21, model.bone_lengths_mm)
    starts = np.stack([_flex_finger(x, 2, 90.0), x])
    obs2 = obs.take([0, 0])
    pri = hm.Priors(pose=starts, pose_w=np.ones(starts.shape[:2]))
    fit = hm.fit_frames(model, starts, obs2, CAM, priors=pri, kin=kin)
    only_second = hm.refit_fingers(model, fit, obs2, CAM, priors=pri, kin=kin, rows=np.array([1]))
    # row 0 was not tried; row 1 sits at the true pose, where no hypothesis is lower
    assert np.array_equal(only_second.joints_mm, fit.joints_mm)
    assert np.array_equal(only_second.energy, fit.energy)
    both = hm.refit_fingers(model, fit, obs2, CAM, priors=pri, kin=kin)
    assert np.array_equal(both.joints_mm[1], fit.joints_mm[1])
    assert both.energy[0] < fit.energy[0]


def test_finger_targets_append_each_frames_own_poses():
    rng = np.random.default_rng(0)
    poses = np.stack([_pose(g) for g in ("open", "fist", "open")]) + rng.normal(0, 2, (3, 21, 3))
    flex, abd = hm.finger_targets(MSRA21, poses, np.array([1, 0, 1]), 3)
    g = hm.grid_flexions(MSRA21)
    assert flex.shape == abd.shape == (3, len(g) + 2, len(MSRA21.angle_joints))
    assert np.allclose(flex[:, : len(g)], g) and np.all(np.isnan(abd[:, : len(g)]))
    f_ref, a_ref = MSRA21.joint_angles(poses)
    assert np.allclose(flex[0, len(g)], f_ref[1]) and np.allclose(abd[0, len(g)], a_ref[1])
    assert np.allclose(flex[1, len(g) :], f_ref[[0, 2]])
    assert np.all(np.isnan(flex[0, len(g) + 1])) and np.all(np.isnan(flex[2, len(g) :]))


def test_pose_library_keeps_the_most_different_poses_in_their_palms_frame():
    """The library's first pose is the one nearest all others, the next the farthest from it;
    a library pose turned into the palm of that same reference moved rigidly is that moved
    reference (the library keeps articulation, the start keeps the frame's hand where it is)."""
    open_, fist = _pose("open"), _pose("fist", ypr=(0.4, -0.3, 0.2), centre=(20.0, 10.0, 450.0))
    near_open = _pose("open", ypr=(0.1, 0.0, 0.0))
    lib = hm.pose_library(MSRA21, np.stack([open_, fist, near_open, _pose("relaxed")]), 2)
    assert lib.shape == (2, 21, 3)
    assert np.allclose(lib[:, MSRA21.root], 0.0)
    moved = fist @ _rot(np.array([0.2, 1.0, 0.3]), 35.0).T + [5.0, -40.0, 30.0]
    starts = hm.library_starts(MSRA21, lib, moved[None])  # (1, 2, 21, 3)
    err = np.linalg.norm(starts[0] - moved, axis=-1).max(axis=1)
    assert err.min() < 1e-6 and err.max() > 30.0  # the fist is in the library, so is an open hand
    # fewer poses than asked: all of them; no finite pose: an empty library
    assert hm.pose_library(MSRA21, np.stack([open_, fist]), 8).shape == (2, 21, 3)
    assert hm.pose_library(MSRA21, np.full((2, 21, 3), np.nan), 8).shape == (0, 21, 3)


@pytest.mark.parametrize("gesture,tol", [("claw", 0.5), ("rock", 6.0)])
def test_a_reference_pose_recovers_fingers_the_start_carried_the_wrong_way(gesture, tol):
    """The depth shows several fingers curled, the start (an open hand in the same palm, with
    the flow's priors on it) has them extended: the plain fit and the one-finger-at-a-time
    hypotheses stay > 5 mm off (the claw 6.4 mm since stop 49, > 10 before); the reference pose of the same gesture, seen elsewhere and at
    another orientation, turned into the fit's palm and fitted without the flow's priors,
    comes back to ``tol`` with a lower energy than the fit's without those priors."""
    x = _pose(gesture, ypr=(0.3, 0.2, 0.1))
    model = _model(x)
    obs = _observe(model, [x])
    start = _pose("open", ypr=(0.3, 0.2, 0.1))
    start = start - start[MSRA21.root] + x[MSRA21.root]
    pri = hm.Priors(
        pose=start[None], pose_w=np.ones((1, 21)), uv=CAM.project(start)[None],
        uv_w=np.ones((1, 21)),
    )  # fmt: skip
    kin = hm.Kinematics(MSRA21, model.bone_lengths_mm)
    fit = hm.refit_fingers(
        model, hm.fit_frames(model, start[None], obs, CAM, priors=pri, kin=kin), obs, CAM,
        priors=pri, kin=kin,
    )  # fmt: skip
    assert np.linalg.norm(fit.joints_mm[0] - x, axis=1).max() > 5.0
    refs = np.stack(
        [_pose("open"), _pose(gesture, ypr=(-0.4, 0.5, 0.0), centre=(30.0, -20.0, 450.0)),
         _pose("spread")]
    )  # fmt: skip
    starts = hm.library_starts(MSRA21, hm.pose_library(MSRA21, refs, 8), fit.joints_mm)[0]
    energy = hm.frame_energy(
        model, kin, *kin.fit(starts), obs.take([0] * len(starts)), CAM, hm.FitWeights(),
        diagnostics=False,
    )[0]  # fmt: skip
    lib = hm.fit_frames(model, starts[np.argmin(energy)][None], obs, CAM, kin=kin)
    assert np.linalg.norm(lib.joints_mm[0] - x, axis=1).max() <= tol
    assert lib.energy[0] < fit.energy[0] - fit.terms["pose"][0] - fit.terms["uv"][0]


def test_a_finger_past_the_image_border_keeps_its_fit():
    """Past the image's border the sensor saw nothing, so no hypothesis of a finger lying there
    can be judged: a finger with no joint on the image stays as fitted. Here the middle finger
    is stuck flexed 90 degrees; seen in full the hypotheses bring it back; with the image cut 3
    px below the stuck finger's joints they moved it 42 mm (its capsules reach into the image off
    the hand, so any swing further out lowered the energy; a tune-part recording had its
    out-of-view thumb swung 180 mm away so), and now leave it."""
    x = _pose("open")
    model = _model(x)
    kin = hm.Kinematics(MSRA21, model.bone_lengths_mm)
    start = _flex_finger(x, 2, 90.0)
    pri = hm.Priors(pose=start[None], pose_w=np.ones((1, len(x))))
    joints = MSRA21.angle_children[hm.finger_chains(MSRA21)[2]]

    def observe(camera):
        a, b = model.capsules(x[None])
        empty = np.zeros((0, 3))
        prims = Primitives(a[0], b[0], model.radii, empty, np.zeros((0, 3, 3)), empty)
        c = x.mean(axis=0)
        crops = crop_depth(render_depth(prims, camera), camera, c)[None]
        return hm.observe(crops, crop_boxes(c, camera)[None], c[None], camera)

    # the image's top edge 3 px below the stuck finger's lowest joint
    cut = CAM.model_copy(update={"cy": CAM.cy - CAM.project(start[joints])[:, 1].max() - 3.0})
    assert np.all(cut.project(start[joints])[:, 1] < -0.5)
    for camera in (CAM, cut):
        obs = observe(camera)
        fit = hm.fit_frames(model, start[None], obs, camera, priors=pri, kin=kin, iterations=0)
        out = hm.refit_fingers(model, fit, obs, camera, priors=pri, kin=kin)
        if camera is cut:
            np.testing.assert_array_equal(out.joints_mm[0, joints], fit.joints_mm[0, joints])
        else:
            assert np.linalg.norm(out.joints_mm[0] - x, axis=1).max() <= 2.0
