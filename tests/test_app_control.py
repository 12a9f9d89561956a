"""The application layer without a browser (app.control): topics of journal entries, the review
walk and review edits as journal entries, the context's options, the drawn joints."""

from __future__ import annotations

import contextlib
import time
from pathlib import Path

import numpy as np
import pytest
from review_session import STEP, open_review_session, synth_data

from app.control.annotate import AnnotateState, display_joints
from app.control.context import AppContext
from app.control.events import EventBus, Update, UpdateTopic, entry_update
from app.control.jobs import ReviewRunner
from app.control.live import LiveResults
from app.control.review import NEIGHBOUR_RADIUS, ReviewState
from handanno_core.annotation import FrameAnnotation
from handanno_core.camera import CameraIntrinsics
from handanno_core.results import Stage, update_lifted
from handanno_core.review import rank_priority
from handanno_core.session import (
    SetFrameAnnotation,
    SetJoint2D,
    SetOutside,
    SetReview,
    SetVisibility,
)

FRAMES = 40


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory) -> Path:
    return synth_data(tmp_path_factory, "control-data", FRAMES, seed=2)


@pytest.fixture()
def session(data_dir, tmp_path):
    yield from open_review_session(tmp_path / "sess", data_dir)


@pytest.fixture()
def review(session):
    """A ReviewState over propagated-looking results: every frame has the ground truth, shifted
    by ``f`` mm on odd frames so frames differ; priority replaced by a known ramp."""
    gt = session.open_sequence().ground_truth.joints_mm
    session.save_results(init_mm=gt + 0.0, confidence=np.ones(gt.shape[:2]))
    live = LiveResults(session)
    runner = ReviewRunner(session, live, propagate_fn=lambda *a, **k: None, debounce_s=3600)
    state = ReviewState(session, live, runner, client="tester")
    yield state
    runner.stop()


def set_priority(state: ReviewState, priority: np.ndarray) -> None:
    state.live.priority = lambda: priority  # type: ignore[method-assign]
    state.live.ranking = lambda wait_s=None: priority  # type: ignore[method-assign]


# ------------------------------------------------------------------------------------------ events
def test_entry_topics_frame_and_joints(session):
    e = session.execute(SetJoint2D(frame=0, joint=3, uv_px=(10.0, 20.0)), client="a")
    u = entry_update(e, session.skeleton.num_joints)
    assert u.topics == {UpdateTopic.ANNOTATION} and u.frame == 0 and u.joints == (3,)
    assert u.client == "a" and u.seq == e.seq
    r = entry_update(session.execute(SetReview(frame=5, status="flagged"), client="a"), 21)
    assert r.topics == {UpdateTopic.REVIEW} and r.frame == 5 and r.joints == ()
    undo = entry_update(session.undo(client="a"), 21)  # the review, then the click
    assert undo.topics == {UpdateTopic.REVIEW} and undo.joints == ()
    back = session.undo(client="a")
    assert back.command["kind"] == "set_joint"
    undo = entry_update(back, 21)
    assert undo.topics == {UpdateTopic.ANNOTATION} and undo.frame == 0 and undo.joints == (3,)
    session.execute(SetVisibility(frame=0, joint=3, visible=False), client="a")
    back = session.undo(client="a")
    assert back.command["kind"] == "set_joint"  # of the flag alone
    flags = entry_update(back, 21)
    assert flags.topics == {UpdateTopic.ANNOTATION} and flags.joints == ()


def test_bus_keeps_publishing_when_a_subscriber_fails():
    bus, got = EventBus(), []
    bus.subscribe(lambda u: 1 / 0)
    unsubscribe = bus.subscribe(got.append)
    bus.publish(Update(frozenset({UpdateTopic.JOB})))
    unsubscribe()
    bus.publish(Update(frozenset({UpdateTopic.JOB})))
    assert len(got) == 1


def test_context_takes_runner_options_and_publishes_edits(session):
    ctx = AppContext(session, lift_fn=None, review_options={"debounce_s": 0.25, "workers": 2})
    try:
        assert ctx.runner.debounce_s == 0.25 and ctx.runner.workers == 2
        got: list[Update] = []
        ctx.bus.subscribe(got.append)
        session.execute(SetJoint2D(frame=10, joint=1, uv_px=(50.0, 60.0)), client="b")
        edits = [u for u in got if UpdateTopic.ANNOTATION in u.topics]
        assert [(u.frame, u.joints, u.client) for u in edits] == [(10, (1,), "b")]
    finally:
        ctx.stop()  # also closes the session (the fixture's close is then a no-op)


# ------------------------------------------------------------------------------------------ review
def test_next_worst_skips_references_reviewed_walked_and_neighbours(review):
    n = review.session.num_frames
    priority = np.linspace(0.0, 1.0, n)  # the last frame is the worst
    set_priority(review, priority)
    review.session.execute(SetReview(frame=n - 1, status="accepted"), client="x")
    review.session.execute(SetReview(frame=n - 2, status="flagged"), client="x")
    first = review.next_worst()
    assert first == n - 3  # not a reviewed frame (accepted or flagged), not a reference
    second = review.next_worst()
    assert second == n - 3 - NEIGHBOUR_RADIUS - 1  # neighbours of the frame just shown wait
    refs = set(range(0, n, STEP))
    walk = [first, second] + [review.next_worst() for _ in range(n)]
    shown = [f for f in walk if f is not None]
    assert not refs & set(shown) and len(shown) == len(set(shown))  # never twice, no reference
    assert len(shown) == n - len(refs) - 2  # neighbours come once nothing else is left
    assert walk[-1] is None


def test_accept_journals_and_advances(review):
    set_priority(review, np.linspace(0.0, 1.0, review.session.num_frames))
    review.go_to(13)
    entry = review.accept()
    assert entry.command == {"frame": 13, "kind": "set_review", "status": "accepted"}
    assert review.frame != 13 and review.session.model.review["13"] == "accepted"


def test_a_correction_unflags_the_frame_in_the_same_entry(review):
    session = review.session
    review.go_to(15)
    review.flag()
    shown, _ = review.live.frame(15)
    target = shown[4] + [5.0, 0.0, 0.0]
    entry = review.move_joint(4, target, shown, None)
    assert "15" not in session.model.review, "a corrected frame is still flagged"
    assert 15 in session.reference_frames
    assert np.allclose(session.annotation(15).xyz_mm[4], target, atol=0.01)
    session.undo("tester")  # one undo step brings the flag back and the reference away
    assert session.model.review.get("15") == "flagged" and 15 not in session.reference_frames
    assert entry.command["kind"] == "batch"


def test_a_frame_without_skeleton_cannot_be_corrected(review):
    with pytest.raises(ValueError, match="no skeleton"):
        review.move_joint(0, np.zeros(3), np.full((21, 3), np.nan), None)


def test_live_priority_is_the_engines_evidence_ranking(review):
    session = review.session
    expected = rank_priority("evidence", session, session.load_results(), None)
    np.testing.assert_allclose(review.live.priority(), expected, equal_nan=True)


def test_background_ranking_follows_the_results_and_updates_only_changed_frames(data_dir, tmp_path):
    """The ranking thread ranks the current results, again after a change, and its incremental
    unexplained-foreground term equals the engine's full computation."""
    from large_session import build_large_session

    from handanno_core.export import best_joints
    from handanno_core.prefill import cached_crops
    from handanno_core.review import unexplained_foreground
    from handanno_core.session import Session

    folder = build_large_session(tmp_path / "big", data_dir, 3, crop_size=32)
    session = Session.open(folder)
    ranked: list[int] = []
    live = LiveResults(session, on_ranked=ranked.append)
    try:
        first = live.ranking(wait_s=None)
        crop_data = cached_crops(session)
        expected = rank_priority("evidence", session, session.load_results(), crop_data)
        np.testing.assert_array_equal(first, expected)
        assert ranked == [live.version]
        moved = live.frame(5)[0] + 30.0
        live.put(5, moved, None, Stage.REFINED)
        second = live.ranking(wait_s=None)
        results = {k: v.copy() for k, v in live.results.items()}
        np.testing.assert_array_equal(
            second, rank_priority("evidence", session, results, crop_data)
        )
        assert second[5] != first[5] and ranked[-1] == live.version
        crops, _, boxes = crop_data
        full = unexplained_foreground(
            best_joints(results)[0], crops, boxes, session.camera, session.skeleton.bones
        )
        np.testing.assert_array_equal(live._ux, full)
    finally:
        live.stop_ranking()
        session.close()


@contextlib.contextmanager
def _ranked_session(data_dir, tmp_path, monkeypatch, copies: int, per_ranking: int):
    """A large session's LiveResults with its ranking thread, at most ``per_ranking`` finger
    ambiguities per ranking; yields (session, live, the versions each ranking published)."""
    from large_session import build_large_session

    from app.control import live as live_module
    from handanno_core.session import Session

    monkeypatch.setattr(live_module, "AMBIGUITY_FRAMES_PER_RANKING", per_ranking)
    session = Session.open(build_large_session(tmp_path / "big", data_dir, copies, crop_size=32))
    ranked: list[int] = []
    live = LiveResults(session, on_ranked=ranked.append)
    try:
        yield session, live, ranked
    finally:
        live.stop_ranking()
        session.close()


def test_a_large_sessions_first_ranking_comes_without_the_ambiguity_which_then_fills_in(
    data_dir, tmp_path, monkeypatch
):
    """The finger ambiguity costs tens of ms per frame: a session with more frames than one ranking
    computes is ranked first without it, then ranked again, a part at a time, without any change
    of the results, until the ranking is the engine's full one."""
    from handanno_core.prefill import cached_crops

    with _ranked_session(data_dir, tmp_path, monkeypatch, 2, 40) as (session, live, ranked):
        first = live.ranking(wait_s=None)
        crop_data = cached_crops(session)
        results = session.load_results()
        without = rank_priority(
            "evidence", session, results, crop_data, ambiguity=np.full(len(first), np.nan)
        )
        np.testing.assert_array_equal(first, without)
        expected = rank_priority("evidence", session, results, crop_data)
        assert not np.array_equal(expected, without, equal_nan=True)
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline:
            if np.array_equal(live._ranked[1], expected, equal_nan=True):
                break
            time.sleep(0.2)
        np.testing.assert_array_equal(live._ranked[1], expected)
        # about one ranking per 40 frames, all of the same results version
        assert len(ranked) >= session.num_frames // 40 and set(ranked) == {live.version}


def test_no_ambiguity_frames_per_ranking_turns_the_term_off(data_dir, tmp_path, monkeypatch):
    from handanno_core.prefill import cached_crops

    with _ranked_session(data_dir, tmp_path, monkeypatch, 1, 0) as (session, live, ranked):
        first = live.ranking(wait_s=None)
        off = np.full(session.num_frames, np.nan)
        expected = rank_priority(
            "evidence", session, session.load_results(), cached_crops(session), ambiguity=off
        )
        np.testing.assert_array_equal(first, expected)
        time.sleep(1.0)  # nothing left to fill in: no further ranking of the same results
        assert ranked == [live.version]


def test_unexplained_foreground_of_some_frames_equals_all_frames(data_dir, tmp_path):
    from large_session import build_large_session

    from handanno_core.export import best_joints
    from handanno_core.prefill import cached_crops
    from handanno_core.review import unexplained_foreground
    from handanno_core.session import Session

    session = Session.open(build_large_session(tmp_path / "big", data_dir, 2, crop_size=32))
    crops, _, boxes = cached_crops(session)
    joints = best_joints(session.load_results())[0]
    args = (crops, boxes, session.camera, session.skeleton.bones)
    full = unexplained_foreground(joints, *args)
    assert np.isfinite(full).all() and np.ptp(full) > 0
    some = unexplained_foreground(joints, *args, frames=np.array([7, 3, 70]), chunk_frames=2)
    np.testing.assert_array_equal(some[[3, 7, 70]], full[[3, 7, 70]])
    assert np.isnan(np.delete(some, [3, 7, 70])).all()
    np.testing.assert_array_equal(unexplained_foreground(joints, *args, chunk_frames=5), full)
    session.close()


# ------------------------------------------------------------------------------------------ results
def test_update_lifted_writes_only_the_given_frames(session):
    before = session.load_results()
    joints = np.full((21, 3), 7.0)
    update_lifted(session, {3: (joints, None)})
    after = session.load_results()
    assert np.all(after["lifted_mm"][3] == 7.0) and np.all(after["confidence"][3] == 1.0)
    np.testing.assert_array_equal(after["lifted_mm"][:3], before["lifted_mm"][:3])
    assert Stage.REFINED > Stage.PROPAGATED > Stage.LIFTED > Stage.NONE == 0


# ------------------------------------------------------------------------------------------ annotate
def test_undo_selects_the_undone_joint(session):
    state = AnnotateState(session, client="u")
    state.place_2d(np.array([100.0, 100.0]))
    placed = state.joint - 1
    state.select_joint(10)
    state.undo()
    assert state.joint == placed


def test_a_joint_marked_outside_the_image_completes_the_frame_and_is_never_accepted(session):
    """A reference whose hand leaves the view: the joints nobody can click are marked outside the
    image (O), after which the frame counts as complete, "accept guesses" leaves them alone, and
    one undo (or X) takes a mark away."""
    session.execute(SetFrameAnnotation(frame=session.reference_frames[0], annotation=None))
    state = AnnotateState(session, client="u")
    frame, j = state.frame, session.skeleton.num_joints
    done = session.progress()[0]
    assert frame == session.reference_frames[0] and not session.is_annotated(frame)
    guesses = np.tile([0.0, 0.0, 400.0], (j, 1))  # every guess drawn at the image's centre
    state.select_joint(20)
    state.toggle_outside()
    assert state.joint == 0  # the next unplaced joint
    assert state.joint_text()[0] == "visible"
    state.select_joint(16)
    state.toggle_outside()
    state.accept_guesses(guesses)
    ann = session.annotation(frame)
    assert ann.outside[[16, 20]].all() and not ann.annotated[[16, 20]].any()
    assert ann.annotated.sum() == j - 2 and session.is_annotated(frame)
    assert session.progress()[0] == done + 1
    again = type(session).open(session.folder)  # replayed from the journal
    assert again.annotation(frame).outside[[16, 20]].all() and again.is_annotated(frame)
    again.close()
    state.undo()  # the accepted guesses
    state.undo()  # the mark of joint 16
    ann = session.annotation(frame)
    assert not ann.outside[16] and ann.outside[20] and not session.is_annotated(frame)
    state.select_joint(20)
    assert state.joint_text()[0] == "outside the image"
    state.clear_joint()
    assert not session.annotation(frame).outside.any()


def test_display_joints_edited_joints_follow_their_annotation():
    camera = CameraIntrinsics(fx=200.0, fy=200.0, cx=64.0, cy=64.0, width=128, height=128)
    ann = FrameAnnotation.empty(3)
    ann.xyz_mm[1] = (0.0, 0.0, 400.0)
    ann.uv_px[2] = (64.0, 64.0)
    lifted = np.array([[1.0, 1.0, 300.0], [2.0, 2.0, 300.0], [3.0, 3.0, 300.0]])
    depth = np.full((128, 128), 350.0, np.float32)
    out = display_joints(ann, camera, depth, np.array([0, 0, 300.0]), lifted_mm=lifted, stale=[1])
    assert np.allclose(out[0], lifted[0]) and np.allclose(out[2], lifted[2])
    assert np.allclose(out[1], (0.0, 0.0, 400.0))  # edited after the lift: its annotation
    first = display_joints(ann, camera, depth, np.array([0, 0, 300.0]))
    assert np.allclose(first[2], (0.0, 0.0, 350.0))  # 2D only: on the depth surface
    assert np.all(np.isnan(first[0]))


def test_a_joint_marked_outside_the_image_is_not_drawn_on_it():
    """The live lift may put a marked joint on the image; it is not drawn there (the annotator
    said it is not on the image), but a position past the border is still drawn."""
    camera = CameraIntrinsics(fx=200.0, fy=200.0, cx=64.0, cy=64.0, width=128, height=128)
    ann = FrameAnnotation.empty(3)
    ann.mark_outside([1, 2])
    lifted = np.array([[1.0, 1.0, 300.0], [2.0, 2.0, 300.0], [300.0, 3.0, 300.0]])
    out = display_joints(ann, camera, None, np.array([0, 0, 300.0]), lifted_mm=lifted)
    assert np.allclose(out[0], lifted[0])
    assert np.all(np.isnan(out[1]))  # on the image: not drawn
    assert np.allclose(out[2], lifted[2])  # projects to u = 264 px, past the border


def test_first_guess_of_a_fresh_session_is_hand_shaped(data_dir, tmp_path):
    """Nothing in the session has joints: the first guess is a template hand at the frame's hand
    centre (bone lengths of the template, spread in 2D), not joints hung off the wrist in a line."""
    from handanno_core.pipeline import new_session

    session = new_session(tmp_path / "fresh", data_dir, format="msra", overwrite=True)
    ctx = AppContext(session, lift_fn=None)
    try:
        guess = ctx.prefill(0)
        centre = ctx.frames.get(0).geometry.centre_mm
    finally:
        ctx.stop()
    assert guess is not None and guess.shape == (21, 3)
    sk = session.skeleton
    np.testing.assert_allclose(
        sk.bone_lengths(guess), np.asarray(sk.template_bone_lengths_mm), rtol=1e-6
    )
    s = np.linalg.svd(guess - guess.mean(axis=0), compute_uv=False)
    assert s[1] > 0.3 * s[0], f"a column, not a hand: singular values {s}"
    np.testing.assert_allclose(guess.mean(axis=0), centre, atol=1e-6)


def test_lift_warns_about_incomplete_references(session, capsys):
    from app.cli import warn_incomplete_references

    assert warn_incomplete_references(session) == []  # every reference fully annotated
    session.execute(SetJoint2D(frame=10, joint=5, uv_px=None), client="t")
    empty = FrameAnnotation.empty(21).to_json()
    session.execute(SetFrameAnnotation(frame=20, annotation=empty), client="t")
    lines = warn_incomplete_references(session)
    assert len(lines) == 2
    assert "1 of 4 reference frames are only partly annotated (frames 10)" in lines[0]
    assert "(frames 20): they are not lifted" in lines[1]
    assert "handanno: warning: 1 of 4" in capsys.readouterr().err
    session.execute(SetOutside(frame=10, joint=5, outside=True), client="t")  # past the border
    assert len(warn_incomplete_references(session)) == 1


def test_frame_store_names_the_source_file(session):
    from app.control.frames import FrameStore

    store = FrameStore(session)
    name = store.source_name(3)
    assert name == session.open_sequence().frame_names[3]
    assert (Path(session.model.dataset.path) / name).is_file()
    assert store.source_name(session.num_frames) is None


def test_joint_legend_shows_placed_occluded_and_selected():
    from app.ui.theme import joint_legend

    ann = FrameAnnotation.empty(3)
    ann.uv_px[0] = (1.0, 2.0)
    ann.visible[1] = False
    ann.uv_px[2] = (3.0, 4.0)
    ann.accepted[2] = True
    colours = np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255]], np.uint8)
    html = joint_legend(["wrist", "index_mcp", "index_tip"], colours, ann, selected=2)
    rows = html.split("<tr")[1:]
    assert "●" in rows[0] and "○" in rows[1] and "◐" in rows[2]  # placed / not / accepted
    assert "occluded" in rows[1] and "opacity" in rows[1] and "occluded" not in rows[0]
    assert "font-weight:bold" in rows[2] and "rgb(0,0,255)" in rows[2]
    assert "I-tip" in rows[2]
    ann.uv_px[0] = np.nan
    ann.outside[0] = True
    rows = joint_legend(["wrist", "index_mcp", "index_tip"], colours, ann, 2).split("<tr")[1:]
    assert "⊘" in rows[0] and "outside the image" in rows[0]


def test_hand_diagram_draws_every_joint_and_bone_placed_filled():
    from app.ui.theme import hand_diagram_svg, joint_colours, load_colours
    from handanno_core.skeleton import MSRA21
    from handanno_core.synth import template_hand

    xy = template_hand(MSRA21, np.zeros(3))[:, :2]
    ann = FrameAnnotation.empty(21)
    ann.uv_px[[0, 4]] = 1.0
    ann.visible[7] = False
    colours = joint_colours(MSRA21.parent_array, load_colours())
    svg = hand_diagram_svg(xy, MSRA21.bones, colours, ann, selected=4)
    assert svg.count("<line") == len(MSRA21.bones)
    joints = [c for c in svg.split("<circle")[1:] if 'class="joint-' in c]
    assert len(joints) == 21
    filled = [k for k, c in enumerate(joints) if 'fill="none"' not in c]
    assert filled == [0, 4]
    assert 'opacity="0.4"' in joints[7] and 'opacity="1"' in joints[6]
    # the fingertips spread across the diagram (a hand, not a column)
    tips = xy[[4, 8, 12, 16, 20]]
    assert np.ptp(tips[:, 0]) > 30.0
