"""Review logic without a browser: scores, worst-frame walk, corrections, the background runner
(streaming, cancelling, re-propagating only descendants), and safe session names."""

from __future__ import annotations

import hashlib
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from review_session import open_review_session, synth_data

from app.control.jobs import PARTIAL_FILE, ReviewRunner
from app.control.live import LiveResults
from handanno_core.camera import CameraIntrinsics
from handanno_core.review import (
    OFF_HAND_MM,
    bone_anomaly,
    correction_command,
    depth_residuals,
    frame_scores,
    next_worst,
    temporal_jump,
    worst_order,
)
from handanno_core.session import (
    JOURNAL_FILE,
    RESULTS_FILE,
    Session,
    SessionError,
    resolve_session,
    safe_session_path,
)
from handanno_core.skeleton import MSRA21

FRAMES = 40


# ------------------------------------------------------------------------------------------ scores
def smooth_sequence(n: int = 30) -> np.ndarray:
    """(n, J, 3) mm: a template hand drifting slowly (bone lengths exact)."""
    rng = np.random.default_rng(0)
    base = rng.normal(0.0, 30.0, size=(MSRA21.num_joints, 3)) + [0.0, 0.0, 400.0]
    drift = np.linspace(0.0, 20.0, n)[:, None, None] * np.array([1.0, 0.0, 0.0])
    return base[None] + drift


def test_bone_anomaly_and_jump_find_the_broken_frame():
    joints = smooth_sequence()
    bones = MSRA21.bones
    lengths = MSRA21.bone_lengths(joints[0])
    joints[12, 4] += [
        0.0,
        45.0,
        0.0,
    ]  # one joint of frame 12 thrown off: a bone stretches, frame jumps
    dev = bone_anomaly(joints, bones, lengths)
    assert dev[0] == pytest.approx(0.0, abs=1e-9) and np.argmax(dev) == 12 and dev[12] > 0.2
    jump = temporal_jump(joints)
    assert np.argmax(jump) == 12 and jump[12] > 40.0
    # neighbours jump only to one side, so their min-jump stays small
    assert jump[11] < 5.0 and jump[13] < 5.0
    # a sequence break between 11 and 12 hides that jump; a missing frame is NaN
    joints[20] = np.nan
    jump2 = temporal_jump(joints, sequence_breaks=[12])
    assert np.isnan(jump2[20]) and jump2[12] > 40.0 and jump2[11] < 5.0


def test_frame_scores_rank_bad_frames_first_and_references_are_excluded():
    joints = smooth_sequence()
    lengths = MSRA21.bone_lengths(joints[0])
    conf = np.full(joints.shape[:2], 0.9)
    conf[5] = 0.3  # low propagation confidence
    joints[12, 4] += [0.0, 45.0, 0.0]  # geometric anomaly
    joints[25] = np.nan  # not computed
    is_ref = np.zeros(len(joints), bool)
    is_ref[[0, 10, 20]] = True
    s = frame_scores(conf, joints, MSRA21.bones, lengths, is_reference=is_ref)
    assert np.isnan(s.score[25]) and np.all(s.score[is_ref] == 1.0)
    assert np.all((s.score[np.isfinite(s.score)] >= 0) & (s.score[np.isfinite(s.score)] <= 1))
    order = worst_order(s.score, exclude=np.flatnonzero(is_ref))
    assert set(order[:2]) == {5, 12}
    assert 25 not in order and 0 not in order
    # the depth term moves a frame to the front
    residual = np.zeros(joints.shape[:2])
    residual[7] = 60.0
    s2 = frame_scores(
        conf, joints, MSRA21.bones, lengths, depth_residual_mm=residual, is_reference=is_ref
    )
    assert 7 not in order[:3] and 7 in worst_order(s2.score, np.flatnonzero(is_ref))[:3]
    # the optional flow term too
    flow = np.zeros(len(joints))
    flow[17] = 20.0
    s3 = frame_scores(conf, joints, MSRA21.bones, lengths, flow_error_px=flow, is_reference=is_ref)
    assert 17 not in order[:3] and 17 in worst_order(s3.score, np.flatnonzero(is_ref))[:3]


def test_next_worst_walks_by_increasing_score():
    score = np.array([0.9, 0.2, np.nan, 0.5, 0.1, 0.5])
    assert worst_order(score).tolist() == [4, 1, 3, 5, 0]
    assert next_worst(score) == 4
    assert next_worst(score, 4) == 1
    assert next_worst(score, 1) == 3
    assert next_worst(score, 0) == 4  # wraps around
    assert next_worst(score, 2) == 4  # a frame without score: start from the worst
    assert next_worst(score, None, exclude=[4, 1]) == 3
    assert next_worst(np.full(3, np.nan)) is None


def test_depth_residuals_from_crops():
    cam = CameraIntrinsics(fx=200.0, fy=200.0, cx=63.5, cy=63.5, width=128, height=128)
    n, size, cube = 2, 128, 220.0
    crops = np.ones((n, size, size), np.float32)
    crops[:, 40:90, 40:90] = 0.0  # a flat surface at the centre depth
    centres = np.array([[0.0, 0.0, 400.0]] * n)
    boxes = np.array([[0.0, 0.0, 1.0, 1.0]] * n)  # crop pixel == image pixel
    joints = np.zeros((n, 3, 3))
    joints[:, :, 2] = 410.0  # behind the surface: fine
    joints[0, 1, 2] = 380.0  # 20 mm in front of the surface
    joints[0, 2, :2] = [-60.0, -60.0]  # projects at (33.5, 33.5): background
    res = depth_residuals(joints, crops, boxes, centres, cam, cube_mm=cube)
    assert res[0, 0] == 0.0 and res[0, 1] == pytest.approx(20.0) and res[0, 2] == OFF_HAND_MM
    assert np.all(res[1] == 0.0)
    behind = depth_residuals(joints, crops, boxes, centres, cam, cube_mm=cube, behind=True)
    assert behind[0, 0] == pytest.approx(10.0) and behind[0, 1] == 0.0 and behind[0, 2] == 0.0
    joints[1, 0, 2] = 900.0  # far behind the surface: capped
    behind = depth_residuals(joints, crops, boxes, centres, cam, cube_mm=cube, behind=True)
    assert behind[1, 0] == OFF_HAND_MM


def test_smooth_in_time_and_centre_drift():
    from handanno_core.review import centre_drift, smooth_in_time

    p = np.array([0.0, 0.0, 3.0, 0.0, np.nan, 0.0, 3.0, 3.0, 3.0, 0.0])
    s = smooth_in_time(p, 1, 0.5)
    assert np.isnan(s[4]) and s[2] == pytest.approx(0.5 * 3.0 + 0.5 * 1.0)
    assert s[3] == pytest.approx(0.5 * 1.5)  # the NaN neighbour does not count
    assert s[7] > s[6] > s[5]  # inside a stretch beats its edge
    assert np.array_equal(smooth_in_time(p, 0, 0.5), p, equal_nan=True)
    # a break at 7: frame 6 no longer sees 7
    assert smooth_in_time(p, 1, 0.5, [7])[6] == pytest.approx(0.5 * 3.0 + 0.5 * 1.5)
    joints = np.zeros((4, 3, 3))
    joints[:, :, 0] = [[0.0], [10.0], [20.0], [50.0]]  # the skeleton moves right
    centres = np.array([[0.0, 0.0, 0.0], [10.0, 0, 0], [20.0, 0, 0], [20.0, 0, 0]])
    drift = centre_drift(joints, centres, np.zeros(4, dtype=np.int64))
    assert drift[:3] == pytest.approx([0.0, 0.0, 0.0]) and drift[3] == pytest.approx(30.0)


# ------------------------------------------------------------------------------------------ session fixture
@pytest.fixture(scope="module")
def data_dir(tmp_path_factory) -> Path:
    return synth_data(tmp_path_factory, "review-data", FRAMES, seed=1)


@pytest.fixture()
def session(data_dir, tmp_path):
    yield from open_review_session(tmp_path / "sess", data_dir)


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest() if path.exists() else ""


# ------------------------------------------------------------------------------------------ corrections
def test_correction_makes_a_reference_in_one_undoable_entry(session):
    frame, joint = 13, 4
    gt = session.open_sequence().ground_truth.joints_mm
    shown = gt[frame] + 3.0
    target = gt[frame, joint] + [5.0, 0.0, 0.0]
    with session.lock:
        cmd, became = correction_command(session, frame, joint, target, shown)
        entry = session.execute(cmd, client="a")
    assert became and entry.command["kind"] == "batch"
    kinds = [c["kind"] for c in entry.command["commands"]]
    assert kinds == ["set_reference", "set_frame", "set_3d"]
    assert frame in session.model.selection.reference_frames and session.model.corrections == [
        frame
    ]
    assert session.parent[frame] == -1
    ann = session.annotation(frame)
    assert np.allclose(ann.xyz_mm[joint], target, atol=0.01)
    assert np.allclose(ann.xyz_mm[joint + 1], shown[joint + 1], atol=0.01)
    # a second annotator's edit on the same frame (with a stale skeleton) is a plain joint edit:
    # it cannot re-seed the frame over the first annotator's joint
    with session.lock:
        cmd2, became2 = correction_command(session, frame, 7, gt[frame, 7], gt[frame] - 50.0)
        session.execute(cmd2, client="b")
    assert not became2 and cmd2.kind == "set_3d"
    reopened = Session.open(session.folder)
    assert np.allclose(reopened.annotation(frame).xyz_mm[joint], target, atol=0.01)
    assert np.allclose(reopened.annotation(frame).xyz_mm[7], gt[frame, 7], atol=0.01)
    assert reopened.model.corrections == [frame]
    reopened.close()
    # client a's undo restores the frame to a propagated one without touching b's joint edit
    session.undo("a")
    assert frame not in session.model.selection.reference_frames and session.model.corrections == []
    assert session.parent[frame] == 12


# ------------------------------------------------------------------------------------------ runner
def fake_propagate(delay_s: float = 0.0, gate: threading.Event | None = None):
    """A stand-in for pipeline.propagate: emits each frame's joints, then saves like the real one."""
    calls = []

    def run(session, *, workers=1, frames=None, progress=None, on_result=None, quiet=False):
        parent = session.parent
        todo = (
            np.flatnonzero(parent >= 0)
            if frames is None
            else np.asarray(frames)[parent[frames] >= 0]
        )
        calls.append(todo.tolist())
        results = session.load_results()
        init, conf = results["init_mm"].copy(), results["confidence"].copy()
        j = session.skeleton.num_joints
        for k, f in enumerate(todo):
            if gate is not None and k == len(todo) // 2:
                assert gate.wait(120)
            joints = np.full((j, 3), 100.0 + f) + len(calls)
            on_result(int(f), joints, np.full(j, 0.5))
            progress(k + 1, len(todo))
            init[f], conf[f] = joints, 0.5
            time.sleep(delay_s)
        session.save_results(init_mm=init, confidence=conf)

    run.calls = calls
    return run


def fake_refine(session, progress=None):
    for it in range(3):
        progress(it + 1, 10.0 - it)
    init = session.load_results()["init_mm"]
    return np.where(np.isfinite(init), init + 1.0, np.nan)


def test_runner_streams_then_saves_and_cancel_leaves_old_results(session):
    gate = threading.Event()
    prop = fake_propagate(gate=gate)
    runner = ReviewRunner(session, propagate_fn=prop, refine_fn=fake_refine, checkpoint_every_s=0.0)
    results_path, journal_path = session.folder / RESULTS_FILE, session.folder / JOURNAL_FILE
    before, journal_before = digest(results_path), digest(journal_path)
    seen = []
    runner.listeners.append(lambda ev, r, f: seen.append(f) if ev == "frame" else None)
    try:
        assert runner.start_full()
        assert not runner.start_full()  # one at a time
        deadline = time.monotonic() + 120  # a last resort: the run stops at the gate
        while runner.status.done < 10 and time.monotonic() < deadline:
            time.sleep(0.02)
        # frames are visible while the job is still running (it waits on the gate)
        assert runner.status.running and runner.live.filled() >= 4 + 10
        assert (session.folder / PARTIAL_FILE).exists()  # periodic save next to results.npz
        assert digest(results_path) == before  # results.npz untouched so far
        runner.cancel()
        gate.set()
        assert runner.wait_idle(120)
        assert runner.status.phase == "cancelled"
        assert digest(results_path) == before and digest(journal_path) == journal_before
        assert not (session.folder / PARTIAL_FILE).exists()
        # a complete run writes init and final; the partial file is gone
        gate.set()
        assert runner.start_full() and runner.wait_idle(120)
        assert runner.status.phase == "done", runner.status.message
        res = session.load_results()
        non_refs = np.flatnonzero(session.parent >= 0)
        assert np.all(np.isfinite(res["init_mm"][non_refs])) and np.all(
            np.isfinite(res["final_mm"][non_refs])
        )
        assert sorted(set(seen)) == non_refs.tolist()
        assert runner.live.stage[non_refs].min() == 3
        assert digest(journal_path) == journal_before
    finally:
        runner.stop()


def test_runner_cancel_during_refinement_restores_results(session):
    started = threading.Event()

    def slow_refine(session, progress=None):
        started.set()
        for it in range(6000):  # until cancelled (progress raises); 2 minutes as a last resort
            progress(it, 1.0)
            time.sleep(0.02)
        raise AssertionError("not cancelled")

    runner = ReviewRunner(session, propagate_fn=fake_propagate(), refine_fn=slow_refine)
    before = digest(session.folder / RESULTS_FILE)
    try:
        runner.start_full()
        assert started.wait(120)
        # issue 16: propagation's init_mm waits in memory for refinement; results.npz is untouched
        assert digest(session.folder / RESULTS_FILE) == before
        runner.cancel()
        assert runner.wait_idle(120) and runner.status.phase == "cancelled"
        res = session.load_results()
        assert not np.isfinite(res["init_mm"]).any()  # back to the old (empty) propagation
    finally:
        runner.stop()


def test_correction_repropagates_only_descendants_with_the_real_pipeline(session):
    """Real propagation (DIS aligner) and refinement: after a correction on frame 15 only the
    frames between its neighbouring references are propagated again, 16..19 (its descendants in
    the chain 10 -> 11 -> ... -> 19) and 11..14 (propagated backwards from it, the hand model's
    second candidate), and only those can get a new init_mm on disk."""
    gt = session.open_sequence().ground_truth.joints_mm
    runner = ReviewRunner(session, lift_for=lambda f, seq: gt[f], debounce_s=0.05)
    try:
        assert runner.start_full() and runner.wait_idle(120)
        assert runner.status.phase == "done", runner.status.message
        first = session.load_results()
        non_refs = np.flatnonzero(session.parent >= 0)
        assert np.all(np.isfinite(first["init_mm"][non_refs]))
        err = np.linalg.norm(first["final_mm"] - gt, axis=-1)
        assert np.nanmedian(err) < 25.0, np.nanmedian(err)
        # review edit on frame 15 (as the view does it)
        frame = 15
        shown = first["final_mm"][frame]
        with session.lock:
            cmd, became = correction_command(session, frame, 8, gt[frame, 8], shown)
            entry = session.execute(cmd, client="reviewer")
        assert became
        runner.request_correction(frame, entry.seq)  # wait_idle covers the debounce
        assert runner.wait_idle(120) and runner.status.phase == "done", runner.status.message
        assert runner.status.frames == [11, 12, 13, 14, 16, 17, 18, 19]
        second = session.load_results()
        changed = np.flatnonzero(
            np.any(~np.isclose(second["init_mm"], first["init_mm"], equal_nan=True), axis=(1, 2))
        )
        # a re-propagated frame keeps its earlier pose where that one explains its depth better
        # (pipeline._previous_fits_better), so not every descendant need change
        assert set(changed) <= set(range(11, 20)) and len({16, 17, 18, 19} & set(changed)) >= 2
        assert np.allclose(second["lifted_mm"][frame], gt[frame])
        assert np.all(np.isfinite(second["final_mm"]))
        # refinement moved only those frames: every other one keeps its refined result
        outside = np.setdiff1d(np.arange(session.num_frames), range(11, 20))
        assert np.array_equal(second["final_mm"][outside], first["final_mm"][outside])
        reopened = Session.open(session.folder)
        assert (
            frame in reopened.model.corrections
            and frame in reopened.model.selection.reference_frames
        )
        reopened.close()
    finally:
        runner.stop()


def test_live_results_scores_use_crops_when_cached(session):
    live = LiveResults(session)
    assert live.filled() == 4  # the lifted references
    s = live.scores()
    assert np.isfinite(s.score).sum() == 4 and "depth_mm" not in s.terms  # no crop cache yet
    live.put(3, session.open_sequence().ground_truth.joints_mm[3], np.full(21, 0.8), 2)
    s2 = live.scores()
    assert np.isfinite(s2.score[3]) and s2.score[3] < 1.0


# ------------------------------------------------------------------------------------------ names
@pytest.mark.parametrize(
    "name", ["../etc", "a/b", "/tmp/x", "..", "", ".hidden", "a\\b", "x" * 200]
)
def test_session_names_from_users_are_refused(name, tmp_path):
    with pytest.raises(SessionError):
        safe_session_path(name, tmp_path)


def test_session_names_inside_the_sessions_folder(tmp_path):
    assert safe_session_path("demo", tmp_path) == (tmp_path / "demo").resolve()
    assert resolve_session("demo-2", tmp_path) == (tmp_path / "demo-2").resolve()


# ------------------------------------------------------------------------------------------ engine: rankings
def test_pick_frames_skips_reviewed_and_suppresses_neighbours():
    from handanno_core.review import pick_frames, uniform_pick

    p = np.array([0.1, 0.9, 0.8, 0.7, np.nan, 0.2, 0.6, 0.0, 0.5, 0.3])
    assert pick_frames(p, 3).tolist() == [1, 2, 3]
    assert pick_frames(p, 3, exclude=[2]).tolist() == [1, 3, 6]
    assert 4 not in pick_frames(p, 9).tolist() and len(pick_frames(p, 20)) == 9
    # radius 1: 2 is next to 1 and waits; 3 is not next to 1; then 6, 8; deferred fill the rest
    assert pick_frames(p, 4, radius=1).tolist() == [1, 3, 6, 8]
    assert pick_frames(p, 9, radius=1)[-1] in (2, 5, 7, 9, 0)
    # a sequence break between 1 and 2 makes them independent
    assert pick_frames(p, 2, radius=1, sequence_breaks=[2]).tolist() == [1, 2]
    u = uniform_pick(100, 5, exclude=[0])
    assert len(u) == 5 and 0 not in u and u[0] == 1 and u[-1] == 99


def test_evidence_priority_ignores_missing_terms_and_hops():
    from handanno_core.review import evidence_priority, hops_to_reference

    ev = {"a": np.array([0.0, 1.0, np.nan, 4.0]), "b": np.array([1.0, 0.0, 0.0, 0.0])}
    p = evidence_priority(ev, {"a": (1.0, 1.0), "b": (1.0, 0.5), "model_mm": (5.0, 9.0)})
    assert p[3] > p[1] > p[0] > p[2] == 0.0
    assert hops_to_reference(np.array([-1, 0, 1, 2, -1, 4, 5, 1])).tolist() == [
        0,
        1,
        2,
        3,
        0,
        1,
        2,
        2,
    ]


def test_plausibility_terms_find_mirrored_and_swapped_hands(data_dir):
    from handanno_core.datasets import open_sequence
    from handanno_core.review import angle_violation, finger_order_violation

    gt = open_sequence(data_dir).ground_truth.joints_mm[:10]
    mirrored = gt.copy()
    centre = gt[:, :1]
    mirrored[..., 0] = 2 * centre[..., 0] - gt[..., 0]  # a left hand where the right one is
    assert np.all(angle_violation(mirrored, MSRA21) > angle_violation(gt, MSRA21) + 10.0)
    swapped = gt.copy()
    swapped[:, [4, 8]] = gt[:, [8, 4]]  # index and middle fingertips exchanged
    assert np.all(finger_order_violation(gt, MSRA21) == 0.0)
    assert np.all(finger_order_violation(swapped, MSRA21) > 0.0)
    gt_nan = gt.copy()
    gt_nan[3] = np.nan
    assert np.isnan(angle_violation(gt_nan, MSRA21)[3])


def test_unexplained_foreground_sees_an_uncovered_finger():
    from handanno_core.review import unexplained_foreground

    cam = CameraIntrinsics(fx=200.0, fy=200.0, cx=63.5, cy=63.5, width=128, height=128)
    crops = np.ones((2, 128, 128), np.float32)
    crops[:, 60:68, 20:100] = 0.0  # a horizontal bar of hand
    boxes = np.array([[0.0, 0.0, 1.0, 1.0]] * 2)
    joints = np.zeros((2, 3, 3))
    joints[:, :, 2] = 400.0
    joints[:, :, 0] = np.array([-86.0, 0.0, 72.0]) * 2.0  # a bone chain along the bar
    joints[1, 2, :2] = [0.0, 80.0]  # second frame: the right half of the bar is not covered
    out = unexplained_foreground(joints, crops, boxes, cam, np.array([[0, 1], [1, 2]]))
    assert out[0] < 0.1 and out[1] > 0.3


def test_simulated_fix_moves_only_joints_off_by_more_than_4px(data_dir):
    from handanno_core.datasets import open_sequence
    from handanno_core.review_loop import simulated_fix

    seq = open_sequence(data_dir)
    gt = seq.ground_truth.joints_mm[5]
    cam = seq.camera
    ann, clicks = simulated_fix(gt, gt, seq.depth(5), cam, seq.skeleton)
    assert clicks == 0 and np.allclose(ann.uv_px, cam.project(gt))
    shown = gt.copy()
    shown[[4, 9], 0] += 20.0  # ~12 px off at 400 mm
    shown[[7], 0] += 3.0  # ~2 px off: accepted where drawn
    ann, clicks = simulated_fix(shown, gt, seq.depth(5), cam, seq.skeleton)
    assert clicks == 2
    assert np.allclose(ann.uv_px[[4, 9]], cam.project(gt)[[4, 9]])
    assert np.allclose(ann.uv_px[7], cam.project(shown)[7])
    # seeded as the app seeds a correction: the joints not moved are accepted guesses in 3D where
    # they were shown; a moved joint is a click, its 3D position gone
    assert np.isnan(ann.xyz_mm[[4, 9]]).all() and not ann.accepted[[4, 9]].any()
    keep = np.setdiff1d(np.arange(len(gt)), [4, 9])
    np.testing.assert_allclose(ann.xyz_mm[keep], shown[keep])
    assert ann.accepted[keep].all() and ann.visible.any()


def test_review_rounds_correct_shown_frames_and_repropagate_descendants(session):
    from handanno_core import pipeline
    from handanno_core.propagate import descendants
    from handanno_core.review_loop import effort_to_target, review_rounds

    pipeline.ensure_crops(session, quiet=True)
    pipeline.propagate(session, quiet=True)
    pipeline.refine(session, quiet=True)
    refs = session.reference_frames.tolist()
    # an index fingertip 15 mm off on every propagated frame: each frame shown needs a click
    final = session.load_results()["final_mm"]
    final[np.setdiff1d(np.arange(session.num_frames), refs), 8, 0] += 15.0
    session.save_results(final_mm=final)
    parent_before = session.parent.copy()
    entries = review_rounds(session, rounds=1, budget=2, ranking="evidence", quiet=True)
    first, second = entries
    assert first["frames_touched"] == len(refs) and first["joints_clicked"] == len(refs) * 21
    assert second["corrections"] == 2 and second["frames_touched"] == len(refs) + 2
    assert second["joints_clicked"] == first["joints_clicked"] + second["clicks"]
    shown = sorted(set(session.model.corrections))
    assert not set(shown) & set(refs)
    # re-propagated: the shown frames' descendants in the selection's forest and, with the hand
    # model's both-ways candidates, every frame between their neighbouring references
    now_refs = np.asarray(sorted(set(refs) | set(shown)))
    between = set()
    for f in shown:
        lo = now_refs[now_refs < f].max(initial=-1)
        hi = now_refs[now_refs > f].min(initial=session.num_frames)
        between |= set(range(lo + 1, hi)) - set(now_refs.tolist())
    assert set(descendants(parent_before, shown)) - set(shown) <= between
    assert second["repropagated"] == len(between | set(shown))
    res = session.load_results()
    assert np.all(np.isfinite(res["lifted_mm"][shown])) and np.all(np.isfinite(res["final_mm"]))
    # refined again: only those frames (the 15 mm gone); every other frame keeps its result
    moved = np.linalg.norm(res["final_mm"] - final, axis=-1).max(axis=1)
    assert moved[sorted(between)].min() > 1.0
    untouched = np.setdiff1d(np.arange(session.num_frames), sorted(between | set(now_refs)))
    assert len(untouched) and np.array_equal(res["final_mm"][untouched], final[untouched])
    for key in ("mean_mm", "median_mm", "max_mm", "bad_share", "recall_at_10", "shown_bad"):
        assert key in second
    assert effort_to_target(entries, mean_mm=1e3, bad_share=1.0) == len(refs)
    assert effort_to_target(entries, mean_mm=0.0) is None


def test_a_shown_frame_with_nothing_to_move_is_accepted_not_made_a_reference(session):
    """Skeletons within 4 px of the truth everywhere: the simulated annotator presses Accept on
    every shown frame (as in the app's review), so no reference is added, nothing is lifted,
    re-propagated or refined, and the next round shows other frames."""
    from handanno_core.review_loop import review_rounds

    gt = session.open_sequence().ground_truth.joints_mm
    session.save_results(init_mm=gt + 0.5, final_mm=gt + 0.5)
    refs = session.reference_frames.tolist()
    before = session.load_results()
    entries = review_rounds(session, rounds=2, budget=3, ranking="uniform", quiet=True)
    after = session.load_results()
    for key in ("lifted_mm", "init_mm", "final_mm"):
        np.testing.assert_array_equal(after[key], before[key])
    assert session.reference_frames.tolist() == refs and not session.model.corrections
    accepted = sorted(int(f) for f, s in session.model.review.items() if s == "accepted")
    assert len(accepted) == 6 and not set(accepted) & set(refs)  # two rounds, other frames
    assert [e["frames_touched"] for e in entries] == [len(refs), len(refs) + 3, len(refs) + 6]
    assert [e["accepted"] for e in entries] == [0, 3, 6] and entries[-1]["repropagated"] == 0
    assert entries[-1]["joints_clicked"] == entries[0]["joints_clicked"]


def test_repropagation_keeps_a_previous_pose_that_fits_the_depth_better():
    """A re-propagated frame keeps its previous pose where that pose's hand-model fit level is
    lower (it explains the frame's depth better); without levels, or without a previous pose,
    the new one is taken."""
    from handanno_core.pipeline import _previous_fits_better

    new_fit = np.array([[2.0], [3.0], [1.0], [4.0], [1.0]])
    current = {
        "model_fit": np.array([[1.0], [5.0], [np.nan], [1.0], [0.5]]),
        "init_mm": np.zeros((5, 21, 3)),
    }
    current["init_mm"][3] = np.nan  # never propagated before
    keep = _previous_fits_better(new_fit, current)
    assert keep.tolist() == [True, False, False, False, True]


def test_review_evidence_reads_the_model_fit_of_propagation(session):
    """The propagation's model-fit evidence (results ``model_fit``) reaches the ranking as it
    is, without a refit: a frame whose fit the guard rejected, with a large residual, ranks
    above the same frame without that evidence."""
    from handanno_core.results import MODEL_FIT_TERMS
    from handanno_core.review import evidence_priority, review_evidence

    gt = session.open_sequence().ground_truth.joints_mm
    results = session.load_results()
    assert np.all(np.isnan(results["model_fit"]))  # never propagated with the model
    results["init_mm"] = gt + 1.0
    results["confidence"] = np.full(results["confidence"].shape, 0.9)
    results["model_fit"][7] = [12.0, 30.0, 0.5, 1.0]
    results["model_fit"][8] = [1.0, 1.2, 0.0, 0.0]
    ev = review_evidence(session, results)
    for k, name in enumerate(MODEL_FIT_TERMS):
        np.testing.assert_array_equal(ev[f"model_{name}"], results["model_fit"][:, k])
    weights = {"conf": (0.5, 1.0), "model_data_mm": (1.5, 1.0), "model_rejected": (1.0, 1.0)}
    p = evidence_priority(ev, weights)
    assert p[7] > p[8] >= p[9]  # frame 9: no model evidence (NaN) adds nothing
    session.save_results(model_fit=results["model_fit"])  # a result array like the others
    np.testing.assert_array_equal(session.load_results()["model_fit"], results["model_fit"])
