"""Tests of the synthetic hand sequences and the simulated annotator (handanno_core/synth.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from handanno_core import synth
from handanno_core.camera import MSRA_CAMERA
from handanno_core.datasets import open_sequence
from handanno_core.skeleton import MSRA21

FRAMES = 120


@pytest.fixture(scope="module")
def motion() -> synth.SynthMotion:
    return synth.synthesize_motion(3040, seed=0)


@pytest.fixture(scope="module")
def sequence_dir(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("synth") / "seq"
    path = synth.generate_sequence(out, frames=FRAMES, seed=5, progress=False, workers=1)
    assert path == out
    return out


def _window(padded: np.ndarray, uv: np.ndarray, r: int) -> np.ndarray:
    """Values of a 3-pixel-padded image in the (2r+1)^2 windows around pixels uv: (win, J)."""
    offsets = range(3 - r, 4 + r)
    return np.stack([padded[uv[:, 1] + dy, uv[:, 0] + dx] for dy in offsets for dx in offsets])


def _files(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


# ---------------------------------------------------------------------------- kinematics
def test_joint_angles_within_limits_on_every_frame(motion):
    flex_lim, abd_lim = MSRA21.angle_limits()
    flex, abd = MSRA21.joint_angles(motion.joints_mm)
    tol = 0.5
    assert np.all(flex >= flex_lim[:, 0] - tol) and np.all(flex <= flex_lim[:, 1] + tol)
    assert np.all(abd >= abd_lim[:, 0] - tol) and np.all(abd <= abd_lim[:, 1] + tol)
    # the sequence really uses the range: curled fingers and spread fingers occur
    assert flex[:, 1].max() > 90.0  # index PIP
    assert np.abs(abd[:, 0]).max() > 10.0  # index MCP abduction


def test_fk_parameters_are_the_measured_angles():
    model = synth.make_hand_model(2)
    rng = np.random.default_rng(0)
    params = rng.uniform(synth.PARAM_LO, synth.PARAM_HI, (50, synth.NUM_PARAMS))
    flex, abd = MSRA21.joint_angles(synth.local_pose(model, params))
    flex_idx = [0, 2, 3, 4, 6, 7, 8, 10, 11, 12, 14, 15, 16, 18, 20]
    assert np.allclose(flex, params[:, flex_idx], atol=1e-6)
    assert np.allclose(abd[:, [0, 3, 6, 9, 12, 13]], params[:, [1, 5, 9, 13, 17, 19]], atol=1e-6)


def test_bone_lengths_constant_and_per_seed(motion):
    lengths = MSRA21.bone_lengths(motion.joints_mm)
    assert np.ptp(lengths, axis=0).max() < 1e-6
    template = np.asarray(MSRA21.template_bone_lengths_mm)
    assert not np.allclose(lengths[0], template, atol=0.5)
    other = synth.make_hand_model(1).bone_lengths_mm
    assert not np.allclose(other, motion.model.bone_lengths_mm)
    assert np.all(np.abs(lengths[0] / template - 1) < 0.15)


def test_motion_is_smooth_and_bounded(motion):
    step = np.linalg.norm(np.diff(motion.joints_mm, axis=0), axis=-1).max(axis=1)
    assert step.max() < 12.0  # fast gestures reach ~10 mm/frame
    assert np.median(step) < 4.0
    assert np.percentile(step, 99) > 3.0  # it does move


def test_global_pose_shows_palm_and_back(motion):
    normal_z = MSRA21.palm_normal(motion.joints_mm)[:, 2]
    assert (normal_z < -0.5).mean() > 0.1 and (normal_z > 0.5).mean() > 0.1
    yaw = motion.yaw_pitch_roll_deg[:, 0]
    assert np.ptp(yaw) > 120.0
    z = motion.joints_mm[..., 2]
    assert 200 < z.min() and z.max() < 520
    assert 300 < np.median(z) < 450
    # even a short sequence turns the hand round
    short = MSRA21.palm_normal(synth.synthesize_motion(FRAMES + 80, seed=5).joints_mm)[:, 2]
    assert short.min() < -0.3 and short.max() > 0.3


def test_gestures_are_revisited(motion):
    revisits = [k for k in motion.keyframes if k.revisit_of >= 0]
    assert len(revisits) >= 3
    for k in revisits:
        src = motion.keyframes[k.revisit_of]
        assert src.gesture == k.gesture and src.frame < k.frame
        assert np.abs(src.glob[:3] - k.glob[:3]).max() < 20.0
    assert len({k.gesture for k in motion.keyframes}) >= 8


def test_shorter_sequence_is_a_prefix(motion):
    short = synth.synthesize_motion(150, seed=0)
    assert np.array_equal(short.joints_mm, motion.joints_mm[:150])


# ---------------------------------------------------------------------------- rendering
def test_ray_cast_capsule_and_ellipsoid_are_exact():
    cam = MSRA_CAMERA
    prims = synth.Primitives(
        cap_a=np.array([[-30.0, 0.0, 400.0]]),
        cap_b=np.array([[30.0, 0.0, 400.0]]),
        cap_r=np.array([10.0]),
        ell_c=np.array([[0.0, 60.0, 300.0]]),
        ell_axes=np.eye(3)[None],
        ell_s=np.array([[20.0, 10.0, 5.0]]),
    )
    depth = synth.render_depth(prims, cam)
    assert depth.dtype == np.float32 and depth.shape == (240, 320)
    assert depth[120, 160] == pytest.approx(390.0, abs=1e-3)  # ray along the optical axis
    # a ray through the capsule's end cap: hits the sphere around (30, 0, 400)
    u = 160 + 241.42 * 36.0 / 400.0
    col = int(round(u))
    d = synth._rays(cam)[0][120, col]
    oc = -np.array([30.0, 0.0, 400.0])
    b = d @ oc
    t = -b - np.sqrt(b * b - (oc @ oc - 100.0))
    assert depth[120, col] == pytest.approx(t * d[2], abs=1e-3)
    # the ellipsoid's front pole
    v = int(round(120 + 241.42 * 60.0 / 300.0))
    ray = synth._rays(cam)[0][v, 160]
    o = -np.array([0.0, 60.0, 300.0]) / np.array([20.0, 10.0, 5.0])
    q = ray / np.array([20.0, 10.0, 5.0])
    qa, qb, qc = q @ q, q @ o, o @ o - 1
    t = (-qb - np.sqrt(qb * qb - qa * qc)) / qa
    assert depth[v, 160] == pytest.approx(t * ray[2], abs=1e-3)
    assert depth[0, 0] == 0.0


def test_sensor_noise(motion):
    clean = synth.render_frame(motion.model, motion.joints_mm[10], motion.rotation[10])
    noisy = synth.render_frame(
        motion.model, motion.joints_mm[10], motion.rotation[10], noise_seed=(0, 10)
    )
    again = synth.render_frame(
        motion.model, motion.joints_mm[10], motion.rotation[10], noise_seed=(0, 10)
    )
    assert np.array_equal(noisy, again)
    assert np.all(noisy[clean == 0] == 0)  # background stays empty
    kept = (clean > 0) & (noisy > 0)
    diff = noisy[kept] - clean[kept]
    assert 0.8 < diff.std() < 1.2 and abs(diff.mean()) < 0.1
    dropped = (clean > 0) & (noisy == 0)
    assert 0.005 < dropped.sum() / (clean > 0).sum() < 0.2
    # dropout concentrates on silhouette / discontinuity pixels
    pad = np.pad(clean, 1)
    edge = np.zeros(clean.shape, dtype=bool)
    for nb in (pad[:-2, 1:-1], pad[2:, 1:-1], pad[1:-1, :-2], pad[1:-1, 2:]):
        edge |= np.abs(clean - nb) > 20.0
    assert (dropped & edge).sum() > 0.5 * dropped.sum()


# ---------------------------------------------------------------------------- written sequence
def test_sequence_reads_back(sequence_dir):
    seq = open_sequence(sequence_dir)
    assert len(seq) == FRAMES
    assert seq.camera == MSRA_CAMERA
    gt = seq.ground_truth.joints_mm
    assert gt.shape == (FRAMES, 21, 3)
    expected = synth.synthesize_motion(FRAMES, seed=5).joints_mm
    assert np.allclose(gt, expected, atol=1e-5)
    on_hand = []
    key_on_hand = []
    key_near_hand = []
    for i in range(FRAMES):
        depth = seq.depth(i)
        assert depth.dtype == np.float32 and depth.shape == (240, 320)
        assert np.count_nonzero(depth) > 1500  # the hand is in every frame
        uv = np.rint(MSRA_CAMERA.project(gt[i])).astype(int)
        assert np.all((uv >= 3) & (uv < [317, 237]))
        pad = np.pad(depth, 3)

        hit = (_window(pad, uv, 1) > 0).any(axis=0)
        on_hand.append(hit)
        key_on_hand.append(hit[[0, 1, 5, 9, 13]])
        key_near_hand.append((_window(pad, uv, 3) > 0).any(axis=0)[[0, 1, 5, 9, 13]])
    assert np.mean(on_hand) >= 0.95
    # wrist and MCPs: on the hand in a 3x3 window except where a sensor hole (radius <= 3 px)
    # happens to cover it; always within a 7x7 window
    assert np.mean(key_on_hand) >= 0.99
    assert np.all(key_near_hand)


def test_generation_is_deterministic(tmp_path, sequence_dir):
    a = synth.generate_sequence(tmp_path / "a", frames=40, seed=5, progress=False, workers=2)
    b = synth.generate_sequence(tmp_path / "b", frames=40, seed=6, progress=False, workers=1)
    files_a = _files(a)
    full = _files(sequence_dir)
    for name in (f"{i:06d}_depth.bin" for i in range(40)):
        assert files_a[name] == full[name]  # same seed, other worker count and length
    assert files_a["camera.json"] == full["camera.json"]
    files_b = _files(b)
    assert files_b["000000_depth.bin"] != files_a["000000_depth.bin"]
    assert files_b["joint.txt"] != files_a["joint.txt"]


# ---------------------------------------------------------------------------- simulated annotator
def _pose(gesture: str, yaw: float, seed: int = 0):
    model = synth.make_hand_model(seed)
    params = synth.gesture_library(model)[gesture][None]
    rot = synth.rotation_matrices(np.array([[yaw, 0.0, 0.0]]))
    joints = synth.forward_kinematics(model, params, rot, np.array([[0.0, 0.0, 370.0]]))[0]
    return model, joints, rot[0]


def test_annotator_exact_2d_and_noise(motion):
    ann = synth.simulate_annotation(
        motion.joints_mm[0],
        synth.render_frame(motion.model, motion.joints_mm[0], motion.rotation[0]),
        MSRA_CAMERA,
        MSRA21,
    )
    assert np.array_equal(ann.uv_px, MSRA_CAMERA.project(motion.joints_mm[0]))
    assert np.all(np.isnan(ann.xyz_mm))
    ann.validate(21)
    rng = np.random.default_rng(1)
    depth = np.zeros((240, 320), np.float32)
    errs = []
    for i in range(0, 3000, 30):
        a = synth.simulate_annotation(motion.joints_mm[i], depth, MSRA_CAMERA, MSRA21, 2.0, rng)
        errs.append(a.uv_px - MSRA_CAMERA.project(motion.joints_mm[i]))
        assert not a.visible.any()  # no depth at all -> nothing visible
    errs = np.concatenate(errs)
    assert errs.std() == pytest.approx(2.0, rel=0.08)
    assert abs(errs.mean()) < 0.1


def test_annotator_visibility_with_occlusion():
    model, joints, rot = _pose("open", 0.0)
    depth = synth.render_frame(model, joints, rot)
    ann = synth.simulate_annotation(joints, depth, MSRA_CAMERA, MSRA21)
    assert ann.visible.all()  # open hand, palm to the camera
    model, joints, rot = _pose("fist", 180.0)
    depth = synth.render_frame(model, joints, rot)
    ann = synth.simulate_annotation(joints, depth, MSRA_CAMERA, MSRA21)
    tips = [4, 8, 12, 16]
    assert not ann.visible[tips].any()  # fingertips curled into the palm, seen from the back
    assert ann.visible[[0, 1, 5, 9, 13]].all()  # knuckles and wrist on the back surface
    # a palm-facing fist shows the thumb folded over the fingers
    model, joints, rot = _pose("fist", 0.0)
    ann = synth.simulate_annotation(joints, synth.render_frame(model, joints, rot), MSRA_CAMERA)
    assert ann.visible[[19, 20]].all()


def test_annotator_depth_order():
    joints = np.zeros((21, 3))
    joints[:, 2] = 400.0
    joints[:, 0] = np.arange(21) * 3.0
    joints[1, 2] = 415.0  # index MCP 15 mm farther than the wrist
    joints[2, 2] = 400.0  # index PIP 15 mm closer than its MCP
    joints[3, 2] = 405.0  # DIP 5 mm farther: inside the margin
    ann = synth.simulate_annotation(joints, np.zeros((240, 320), np.float32), MSRA_CAMERA)
    assert ann.depth_order[0] == 0
    assert ann.depth_order[1] == 1 and ann.depth_order[2] == -1 and ann.depth_order[3] == 0
    assert ann.depth_order.dtype == np.int8


def test_simulate_annotations_on_sequence(sequence_dir):
    seq = open_sequence(sequence_dir)
    anns = synth.simulate_annotations(seq, [3, 50, 99], noise_px=1.5, seed=2)
    assert sorted(anns) == [3, 50, 99]
    again = synth.simulate_annotations(seq, [50], noise_px=1.5, seed=2)
    assert np.array_equal(anns[50].uv_px, again[50].uv_px)  # independent of the frame set
    vis = np.mean([a.visible.mean() for a in anns.values()])
    assert 0.3 < vis <= 1.0


# ---------------------------------------------------------------------------- arm and sensors


def test_egocentric_arm_is_nearer_to_the_camera_than_the_hand(motion):
    frames = np.arange(0, 600, 50)
    _, _, dirs = synth.pose_arm(motion.joints_mm[:600], motion.rotation[:600], "egocentric", seed=0)
    assert np.allclose(np.linalg.norm(dirs, axis=1), 1.0)
    assert np.all(dirs[:, 2] < -0.5) and np.all(dirs[:, 1] > 0.0)  # towards the camera, below
    for f in frames[:4]:
        depth = synth.render_frame(
            motion.model, motion.joints_mm[f], motion.rotation[f], forearm_dir=dirs[f]
        )
        valid = depth[depth > 0]
        # the arm is cut before the camera but comes far nearer than the wrist
        assert valid.min() >= synth.NEAR_CLIP_MM
        assert valid.min() < motion.joints_mm[f, 0, 2] - 80.0


def test_arm_modes_cover_directions(motion):
    n = 480
    joints, rotation, top = synth.pose_arm(
        motion.joints_mm[:n], motion.rotation[:n], "top-down", seed=2
    )
    angle = np.degrees(np.arctan2(top[:, 1], top[:, 0])) % 360
    assert np.histogram(angle, bins=8, range=(0, 360))[0].min() > 0  # every in-plane direction
    assert np.all(top[:, 2] > 0)  # the elbow is farther than the wrist
    # the hand turns with the arm: the forearm stays within a wrist's reach of the hand's axis
    axis = joints[:, 5] - joints[:, 0]  # wrist -> middle finger's knuckle
    away = np.degrees(np.arccos(np.sum(top * -axis, 1) / np.linalg.norm(axis, axis=1)))
    assert away.max() < 60.0
    # a turned hand is the same hand, where it was: bones and the joints' mean kept
    assert np.allclose(joints.mean(axis=1), motion.joints_mm[:n].mean(axis=1))
    bones = lambda x: np.linalg.norm(x[:, 1:] - x[:, list(MSRA21.parents[1:])], axis=-1)  # noqa: E731
    assert np.allclose(bones(joints), bones(motion.joints_mm[:n]))
    assert np.allclose(np.einsum("nji,njk->nik", rotation, rotation), np.eye(3), atol=1e-9)
    # a shorter sequence is a prefix of a longer one
    short = synth.pose_arm(motion.joints_mm[:200], motion.rotation[:200], "top-down", seed=2)
    assert np.allclose(short[0], joints[:200]) and np.allclose(short[2], top[:200])
    _, _, wrist = synth.pose_arm(motion.joints_mm[:n], motion.rotation[:n], "wrist", seed=2)
    local = np.einsum("nji,nj->ni", motion.rotation[:n], wrist)  # back to the hand frame
    flex = np.degrees(np.arctan2(local[:, 2], -local[:, 1]))
    assert flex.min() < -40 and flex.max() > 50 and np.all(np.abs(flex) <= 71)
    assert synth.pose_arm(motion.joints_mm, motion.rotation, "hand")[2] is None
    with pytest.raises(ValueError, match="arm mode"):
        synth.pose_arm(motion.joints_mm, motion.rotation, "sideways")


def test_sleeve_widens_the_arm(motion):
    f = 100
    down = -motion.rotation[f][:, 1]
    bare = synth.render_frame(
        motion.model, motion.joints_mm[f], motion.rotation[f], forearm_dir=down
    )
    sleeve = synth.render_frame(
        motion.model, motion.joints_mm[f], motion.rotation[f], forearm_dir=down, sleeve=True
    )
    assert (sleeve > 0).sum() > (bare > 0).sum() * 1.05
    assert np.all(sleeve[bare > 0] > 0)


def test_generate_sequence_with_arm(tmp_path):
    out = synth.generate_sequence(
        tmp_path / "arm", frames=6, seed=1, progress=False, workers=1, arm="egocentric", sleeve=True
    )
    seq = open_sequence(out)
    assert len(seq) == 6
    info = __import__("json").loads((out / "synth.json").read_text())
    assert info["arm"] == {"mode": "egocentric", "sleeve": True, "hand_turned": False}
    depth = seq.depth(0)
    assert depth[depth > 0].min() < seq.ground_truth.joints_mm[0, 0, 2] - 80.0


def test_kinect_sensor_quantizes_disparity_and_flies_pixels(motion):
    f = 30
    joints = motion.joints_mm[f] + np.array([0.0, 0.0, 300.0])  # Kinect range
    clean = synth.render_frame(motion.model, joints, motion.rotation[f])
    depth = synth.render_frame(
        motion.model, joints, motion.rotation[f], noise_seed=(0, f), sensor=synth.KINECT_SENSOR
    )
    s = synth.KINECT_SENSOR
    valid = depth > 0
    disparity = s.disparity_fb / depth[valid].astype(np.float64)
    steps = disparity / s.disparity_step_px
    assert np.allclose(steps, np.round(steps), atol=1e-3)  # only quantized depths
    assert np.unique(np.round(depth[valid])).size < 0.5 * valid.sum()
    flying = valid & (clean == 0)  # measurements where there is no surface
    assert flying.sum() > 20
    assert np.all(depth[flying] > 600.0)  # behind the hand's edge, not in front
    near = synth.render_frame(
        motion.model,
        motion.joints_mm[f] - np.array([0.0, 0.0, 100.0]),
        motion.rotation[f],
        noise_seed=(0, f),
        sensor=synth.KINECT_SENSOR,
    )
    assert not np.any((near > 0) & (near < s.min_range_mm))


def test_sr300_sensor_has_more_holes_and_ragged_edges(motion):
    f = 30
    clean = synth.render_frame(motion.model, motion.joints_mm[f], motion.rotation[f])
    msra = synth.render_frame(
        motion.model, motion.joints_mm[f], motion.rotation[f], noise_seed=(0, f)
    )
    sr = synth.render_frame(
        motion.model,
        motion.joints_mm[f],
        motion.rotation[f],
        noise_seed=(0, f),
        sensor=synth.SR300_SENSOR,
    )
    lost = lambda d: ((clean > 0) & (d == 0)).sum()  # noqa: E731
    assert lost(sr) > 1.5 * lost(msra)
    both = (clean > 0) & (sr > 0)
    err = np.abs(sr[both] - clean[both])
    assert np.percentile(err, 99.5) > 8.0  # noisy edges (MSRA-like: 1 mm Gaussian)
    assert synth.SensorModel() == synth.MSRA_SENSOR
