"""The app's logic without a browser: scene geometry, the annotator's state/commands, the lift
worker (coalescing, errors), the hotkey layer and help text."""

from __future__ import annotations

import threading
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from app.control.annotate import AnnotateState
from app.control.events import entry_frame
from app.control.frames import FrameStore
from app.control.geometry import MAX_CLOUD_POINTS, build_frame_geometry, colormap
from app.control.jobs import LiftWorker
from app.ui.hotkeys import HOTKEYS, REVIEW_HOTKEYS, bind, bind_all, hotkey_table_markdown
from handanno_core.camera import MSRA_CAMERA
from handanno_core.datasets import write_msra_frame
from handanno_core.session import DatasetSpec, Session

CAM = MSRA_CAMERA
STATIC = Path(__file__).resolve().parents[1] / "static"


def hand_depth(shift_px: int = 0) -> np.ndarray:
    """A 320x240 depth map: a palm disc and five finger bars at ~400 mm on an empty background."""
    v, u = np.mgrid[0 : CAM.height, 0 : CAM.width]
    depth = np.zeros((CAM.height, CAM.width), np.float32)
    palm = (u - 160 - shift_px) ** 2 + (v - 140) ** 2 < 35**2
    depth[palm] = 400.0 + 0.05 * (u[palm] - 160)
    for k, du in enumerate((-30, -12, 5, 22, 45)):
        bar = (np.abs(u - 160 - shift_px - du) < 5) & (v > 60 + 5 * k) & (v < 115)
        depth[bar] = 395.0
    return depth


def make_session(tmp_path: Path, frames: int = 6, bad_frame: int | None = 3) -> Session:
    data = tmp_path / "data"
    data.mkdir()
    for i in range(frames):
        write_msra_frame(data / f"{i:06d}_depth.bin", hand_depth(2 * i))
    if bad_frame is not None:
        (data / f"{bad_frame:06d}_depth.bin").write_bytes(b"\x00\x01")  # truncated
    session = Session.create(
        tmp_path / "sess", DatasetSpec(path=str(data), format="msra"), frames, CAM
    )
    refs = [0, 3, 5]
    session.set_selection(
        {
            "strategy": "test",
            "reference_frames": refs,
            "parent": [-1 if f in refs else 0 for f in range(frames)],
        }
    )
    return session


@pytest.fixture
def session(tmp_path):
    s = make_session(tmp_path)
    yield s
    s.close()


# ------------------------------------------------------------------ geometry
def test_image_plane_lines_up_with_cloud():
    """Seen from the sensor, every cloud point lies on the ray through its own pixel of the image."""
    depth = hand_depth()
    geo = build_frame_geometry(depth, CAM, np.array([0.0, 20.0, 400.0]))
    assert 0 < len(geo.cloud_mm) <= MAX_CLOUD_POINTS
    rng = np.random.default_rng(0)
    pts = geo.cloud_mm[rng.choice(len(geo.cloud_mm), 20, replace=False)]
    origin = geo.sensor_position
    for p in pts:
        uv = geo.ray_to_pixel(origin, geo.to_scene(p) - origin)
        assert uv is not None
        np.testing.assert_allclose(uv, CAM.project(p), atol=1e-6)
        # ... and that pixel of the image is a hand pixel.
        assert depth[int(round(uv[1])), int(round(uv[0]))] > 0
    # The image node's extent covers exactly the W x H pixels on the plane.
    rw, rh = geo.image_render_size
    corner = geo.pixel_to_scene(np.array([-0.5, -0.5]))
    np.testing.assert_allclose(corner[:2], geo.image_position[:2] - (rw / 2, rh / 2), atol=1e-9)
    assert geo.plane_z_mm > geo.centre_mm[2] + 100  # behind the hand: the cloud stays in front


def test_pixel_round_trip_and_misses():
    geo = build_frame_geometry(hand_depth(), CAM, np.array([0.0, 0.0, 400.0]))
    uv = np.array([[12.0, 200.5], [319.0, 0.0], [160.0, 120.0]])
    for p in uv:
        ray_end = geo.pixel_to_scene(p)
        origin = geo.sensor_position + np.array([0.01, -0.02, 0.0])  # any origin on the ray's side
        got = geo.ray_to_pixel(origin, ray_end - origin)
        np.testing.assert_allclose(got, p, atol=1e-6)
    assert (
        geo.ray_to_pixel(geo.sensor_position, np.array([0.0, 0.0, -1.0])) is None
    )  # away from plane
    assert (
        geo.ray_to_pixel(geo.sensor_position, np.array([1.0, 0.0, 0.01])) is None
    )  # outside image


def test_nearest_cloud_point_snaps_to_front_surface():
    geo = build_frame_geometry(hand_depth(), CAM, np.array([0.0, 20.0, 400.0]))
    target = geo.cloud_mm[len(geo.cloud_mm) // 2]
    origin = geo.sensor_position
    hit = geo.nearest_cloud_point(origin, geo.to_scene(target) - origin)
    assert hit is not None
    assert np.linalg.norm(CAM.project(hit) - CAM.project(target)) < 3.0  # same place on screen
    # A ray into empty space finds nothing.
    assert geo.nearest_cloud_point(origin, np.array([0.0, -1.0, 0.2])) is None


def test_cloud_is_cropped_and_capped():
    depth = np.full((CAM.height, CAM.width), 400.0, np.float32)  # a wall: 76,800 points
    geo = build_frame_geometry(
        depth, CAM, np.array([0.0, 0.0, 400.0]), cube_mm=2000.0, max_points=50_000
    )
    assert len(geo.cloud_mm) <= 50_000
    small = build_frame_geometry(depth, CAM, np.array([0.0, 0.0, 400.0]), cube_mm=100.0)
    assert np.all(np.abs(small.cloud_mm[:, :2]) <= 50.0 + 1e-9)
    assert geo.image_rgb.shape == (CAM.height, CAM.width, 3) and geo.image_rgb.dtype == np.uint8


def test_colormap_endpoints_and_nan():
    c = colormap(np.array([0.0, 1.0, np.nan, -5.0]))
    assert c.shape == (4, 3) and c.dtype == np.uint8
    assert not np.array_equal(c[0], c[1])
    np.testing.assert_array_equal(c[2], c[1])  # NaN -> far
    np.testing.assert_array_equal(c[3], c[0])  # clipped


# ------------------------------------------------------------------ annotator state
def test_place_2d_advances_to_next_unplaced_joint(session):
    st = AnnotateState(session, "browser-1")
    assert st.frame == 0 and st.joint == 0
    e = st.place_2d(np.array([150.0, 130.0]))
    assert e.command["kind"] == "set_2d" and e.client == "browser-1"
    assert st.joint == 1
    st.select_joint(5)
    st.place_2d(np.array([155.0, 100.0]))
    assert st.joint == 6
    st.select_joint(20)
    st.place_2d(np.array([180.0, 120.0]))
    assert st.joint == 1  # wraps to the first unplaced joint
    ann = session.annotation(0)
    np.testing.assert_allclose(ann.uv_px[[0, 5, 20]], [[150, 130], [155, 100], [180, 120]])
    # out-of-image clicks are clamped into the image
    st.place_2d(np.array([-4.0, 999.0]))
    np.testing.assert_allclose(session.annotation(0).uv_px[1], [0.0, CAM.height - 1])


def test_click_on_a_joint_placed_in_3d_replaces_its_3d_position_in_one_undo_step(session):
    st = AnnotateState(session, "browser-1")
    st.place_3d(np.array([10.0, 5.0, 398.0]), joint=4, advance=False)
    entry = st.place_2d(np.array([150.0, 130.0]), joint=4)
    ann = session.annotation(0)
    assert entry.command["kind"] == "batch"
    assert not ann.has_3d[4]  # the lift follows the click, not the old 3D position
    np.testing.assert_allclose(ann.uv_px[4], [150.0, 130.0])
    st.undo()
    ann = session.annotation(0)
    np.testing.assert_allclose(ann.xyz_mm[4], [10.0, 5.0, 398.0])
    np.testing.assert_allclose(ann.uv_px[4], CAM.project(np.array([10.0, 5.0, 398.0])), atol=0.01)


def test_toggles_clear_undo_redo(session):
    st = AnnotateState(session, "browser-1")
    other = AnnotateState(session, "browser-2")
    assert st.cycle_depth_order() is None  # root: nothing to compare with
    st.select_joint(4)
    st.toggle_visibility()
    assert not session.annotation(0).visible[4]
    assert st.joint_text() == ("occluded", "unknown")
    orders = []
    for _ in range(3):
        st.cycle_depth_order()
        orders.append(int(session.annotation(0).depth_order[4]))
    assert orders == [-1, 1, 0]
    st.place_3d(np.array([10.0, 5.0, 398.0]), advance=False)
    ann = session.annotation(0)
    np.testing.assert_allclose(ann.xyz_mm[4], [10, 5, 398])
    np.testing.assert_allclose(ann.uv_px[4], CAM.project(np.array([10.0, 5.0, 398.0])), atol=0.01)
    other.place_2d(np.array([100.0, 100.0]))  # another client's edit is not in my undo stack
    assert st.clear_joint().command["kind"] == "set_3d"
    assert not session.annotation(0).has_3d[4]
    st.undo()
    assert session.annotation(0).has_3d[4]
    st.redo()
    assert not session.annotation(0).has_3d[4]
    assert session.annotation(0).has_2d[0]  # browser-2's edit untouched
    assert st.undo() and st.undo()  # back through the 3D placement
    assert not session.annotation(0).has_3d[4]


def test_navigation_walks_references_and_progress(session):
    st = AnnotateState(session, "c")
    assert st.frames == [0, 3, 5]
    assert st.next_frame() == 3 and st.next_frame() == 5 and st.next_frame() == 5
    assert st.prev_frame() == 3 and st.go_to_index(-7) == 0
    assert st.progress_text() == "0 of 3 reference frames annotated"
    for j in range(session.skeleton.num_joints):
        st.place_2d(np.array([100.0 + j, 100.0]), joint=j)
    assert st.progress_text() == "1 of 3 reference frames annotated"
    assert (
        AnnotateState(session, "d").frame == 3
    )  # a new browser opens on the first unfinished frame


def test_entry_frame(session):
    st = AnnotateState(session, "c")
    st.go_to_index(2)
    assert entry_frame(st.place_2d(np.array([1.0, 2.0]))) == 5


# ------------------------------------------------------------------ frames and worker
def test_frame_without_depth_gives_message_not_exception(session):
    frames = FrameStore(session)
    bad = frames.get(3)
    assert bad.depth is None and "frame 3" in bad.error and len(bad.geometry.cloud_mm) == 0
    assert bad.geometry.image_rgb.shape == (CAM.height, CAM.width, 3)
    good = frames.get(0)
    assert good.error is None and good.depth is not None and len(good.geometry.cloud_mm) > 100
    assert frames.get(0) is good  # cached


def fake_lift(annotation, depth, camera, skeleton, bone_lengths_mm, **_):
    """Test stand-in for lift_frame: back-projects 2D joints at 400 mm, others at the wrist."""
    uv = np.where(
        annotation.has_2d[:, None], annotation.uv_px, annotation.uv_px[annotation.has_2d][0]
    )
    joints = camera.backproject(uv, np.full(len(uv), 400.0))
    return SimpleNamespace(joints_mm=joints, confidence=annotation.has_2d.astype(float))


def test_worker_lifts_after_edits_and_coalesces(session):
    gate, started = threading.Event(), threading.Event()
    calls = []

    def slow_lift(annotation, *args, **kwargs):
        calls.append(annotation.has_2d.sum())
        started.set()
        assert gate.wait(60)
        return fake_lift(annotation, *args, **kwargs)

    results = []
    worker = LiftWorker(
        session, FrameStore(session), lift_fn=slow_lift, on_result=lambda f, o: results.append(o)
    )
    worker.start()
    try:
        st = AnnotateState(session, "c")
        st.place_2d(np.array([150.0, 130.0]))
        worker.submit(0)
        assert started.wait(60)  # the first job is running (blocked on the gate)
        for j in range(1, 4):
            st.place_2d(np.array([150.0 + j, 120.0]))
            worker.submit(0)  # three submits while busy -> one pending job
        gate.set()
        assert worker.wait_idle(60)
        assert len(calls) == 2 and worker.jobs_coalesced == 2
        assert calls[-1] == 4  # the coalesced job saw the newest annotation
        assert [o.frame for o in results] == [0, 0]
        latest = worker.latest[0]
        assert latest.error is None and latest.joints_mm.shape == (21, 3)
        assert latest.journal_seq == session.model.journal_seq
    finally:
        worker.stop()
    lifted = session.load_results()["lifted_mm"]
    np.testing.assert_allclose(lifted[0], worker.latest[0].joints_mm)  # saved on stop


def place_and_lift(st, worker, clicks: int) -> None:
    """``clicks`` 2D clicks on frame 0, each lifted by ``worker`` before the next."""
    for j in range(clicks):
        st.place_2d(np.array([150.0 + j, 130.0]))
        worker.submit(0)
        assert worker.wait_idle(60)


def test_worker_relifts_a_frame_that_needed_slack_in_elastic_mode(session):
    """After a lift that could not meet some depth intervals, the next lift of that frame starts
    in elastic mode with slacks on those joints; once a lift meets them all, lifts go back to
    hard-first."""
    seen = []
    slack_of_call = iter([[4], [4, 8], [], []])

    def lift(annotation, *args, start_elastic=False, elastic_joints=None, **kwargs):
        seen.append((start_elastic, [int(k) for k in elastic_joints]))
        out = fake_lift(annotation, *args, **kwargs)
        out.slack_joints = np.asarray(next(slack_of_call), dtype=np.int64)
        return out

    worker = LiftWorker(session, FrameStore(session), lift_fn=lift).start()
    try:
        place_and_lift(AnnotateState(session, "c"), worker, 4)
        assert worker.latest[0].needed_slack is False
    finally:
        worker.stop()
    assert seen == [(False, []), (True, [4]), (True, [4, 8]), (False, [])]


def test_worker_reports_errors_without_dying(session):
    def broken(*args, **kwargs):
        raise RuntimeError("solver exploded")

    worker = LiftWorker(session, FrameStore(session), lift_fn=broken).start()
    try:
        st = AnnotateState(session, "c")
        worker.submit(0)  # nothing annotated yet
        assert worker.wait_idle(60)
        assert worker.latest[0].error == "nothing annotated yet"
        st.place_2d(np.array([150.0, 130.0]))
        worker.submit(0)
        assert worker.wait_idle(60)
        assert "solver exploded" in worker.latest[0].error
        st.go_to_index(1)  # frame 3: corrupt depth file
        st.place_2d(np.array([150.0, 130.0]))
        worker.submit(3)
        assert worker.wait_idle(60)
        assert "no depth" in worker.latest[3].error
    finally:
        worker.stop()


def test_worker_without_lift_module_is_unavailable(session, monkeypatch):
    import app.control.jobs as w

    monkeypatch.setattr(w, "default_lift_function", lambda: None)
    worker = LiftWorker(session, FrameStore(session))
    assert not worker.available
    worker.submit(0)  # a no-op, not an error
    assert worker.wait_idle(0.1)


# ------------------------------------------------------------------ hotkeys and help
def test_help_md_has_the_hotkey_table():
    help_md = (STATIC / "help.md").read_text()
    assert hotkey_table_markdown() in help_md, (
        "static/help.md is out of date: paste hotkey_table_markdown()"
    )
    assert "## Annotating" in help_md


def test_hotkeys_are_unique_and_bind_through_our_layer():
    combos = [(h.key, h.modifier) for h in HOTKEYS + REVIEW_HOTKEYS]  # one key, one command
    assert len(set(combos)) == len(combos)
    undo = next(h for h in HOTKEYS if h.action == "undo")
    redo = next(h for h in HOTKEYS if h.action == "redo")
    assert (undo.key, undo.modifier, redo.key, redo.modifier) == (
        "Z",
        "cmd/ctrl",
        "Z",
        "cmd/ctrl+shift",
    )

    class FakeHandle:
        def on_trigger(self, fn):
            self.fn = fn
            return fn

    class FakeGui:
        def __init__(self):
            self.added = []

        def add_command(self, label, *, description=None, hotkey=None, modifier=None):
            self.added.append((label, hotkey, modifier))
            return FakeHandle()

    gui = FakeGui()
    fired = []
    handles = bind_all(
        gui, {"undo": lambda c: fired.append(("undo", c)), "redo": lambda c: fired.append("redo")}
    )
    assert [a[1:] for a in gui.added] == [("Z", "cmd/ctrl"), ("Z", "cmd/ctrl+shift")]
    handles["undo"].fn(SimpleNamespace(client="client-7"))
    assert fired == [("undo", "client-7")]
    assert bind(object(), undo, lambda c: None) is None  # no add_command: degrade, don't crash


# ------------------------------------------------------------------ issue 15 (usability)
def test_undo_selects_the_undone_joint_again(session):
    st = AnnotateState(session, "browser-1")
    st.place_2d(np.array([150.0, 130.0]))
    st.place_2d(np.array([152.0, 120.0]))
    assert st.joint == 2
    st.undo()
    assert st.joint == 1 and not session.annotation(0).has_2d[1]
    st.undo()
    assert st.joint == 0 and not session.annotation(0).annotated.any()
    st.go_to_index(1)  # an undo of an edit on another frame leaves this frame's selection
    st.select_joint(7)
    st.redo()
    st.undo()
    assert st.joint == 7


def test_worker_forget_keeps_replaced_lifts_on_disk(session):
    """After "lift all" replaced the references' lifted joints, the worker's older live lifts
    are not written back over them."""
    worker = LiftWorker(session, FrameStore(session), lift_fn=fake_lift, save_after_s=60.0)
    worker.start()
    try:
        AnnotateState(session, "c").place_2d(np.array([150.0, 130.0]))
        worker.submit(0)
        assert worker.wait_idle(5) and 0 in worker.latest
        better = np.full((21, 3), 7.0)
        lifted = session.load_results()["lifted_mm"]
        lifted[0] = better
        session.save_results(lifted_mm=lifted)
        worker.forget([0])
    finally:
        worker.stop()  # saves what it still holds
    np.testing.assert_allclose(session.load_results()["lifted_mm"][0], better)


def test_runner_lifts_first_when_the_session_has_no_bone_lengths(session):
    """A full run on a browser-annotated session (no bone lengths) lifts all references first,
    with progress; "lift all" alone does only that; a lift error fails the job with its text."""
    from app.control.jobs import ReviewRunner
    from handanno_core.session import SessionError

    calls, phases = [], []

    def lift_all(s, *, workers, quiet, progress):
        calls.append(workers)
        for i in range(3):
            progress(i + 1, 3)
        lifted = s.load_results()["lifted_mm"]
        lifted[0] = 1.0  # the one annotated reference
        s.save_results(lifted_mm=lifted)
        s.set_bone_lengths(s.skeleton.template_bone_lengths_mm)

    def propagate(s, **kw):
        phases.append("propagate")

    def refine(s, progress=None):
        phases.append("refine")
        return np.full((s.num_frames, 21, 3), 1.0)

    AnnotateState(session, "c").place_2d(np.array([150.0, 130.0]))
    runner = ReviewRunner(session, propagate_fn=propagate, refine_fn=refine, lift_all_fn=lift_all)
    seen = []
    runner.listeners.append(lambda event, r, f: seen.append((event, r.status.phase)))
    try:
        assert runner.needs_lift()
        assert runner.start_full() and runner.wait_idle(10)
        assert runner.status.phase == "done", runner.status.message
        assert calls == [1] and phases == ["propagate", "refine"]
        assert ("lifted", "lift-all") in seen and ("progress", "lift-all") in seen
        assert not runner.needs_lift()  # bone lengths now, and the lifted pose of frame 0 ...
        assert runner.start_full() and runner.wait_idle(10)
        assert calls == [1]  # ... so the next full run does not lift again
        assert runner.start_lift() and runner.wait_idle(10)  # "Lift all" always lifts
        assert calls == [1, 1] and phases.count("propagate") == 2
        assert runner.status.text() == "done: references lifted, bone lengths estimated"
        # a lift that estimated the annotators' click noise says so
        session.set_click_noise(1.84)
        assert runner.start_lift() and runner.wait_idle(10)
        assert runner.status.text() == (
            "done: references lifted, bone lengths estimated; "
            "clicks: 1.8 px noise (estimated by the last lift)"
        )

        def failing(s, **kw):
            raise SessionError("sess: no annotated reference frames to lift")

        runner.lift_all_fn = failing
        assert runner.start_lift() and runner.wait_idle(10)
        assert runner.status.phase == "failed" and "no annotated reference" in runner.status.text()
    finally:
        runner.stop()


def test_busy_port_is_an_error_naming_the_port(tmp_path):
    import socket

    from app.ui.server import PortInUseError, serve

    s = make_session(tmp_path)
    s.close()
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        with pytest.raises(PortInUseError, match=f"port {port} on 127.0.0.1 is already in use"):
            serve(s.folder, port=port, block=False, lift_fn=fake_lift)
    # the session was closed again: a second open works and sees no edits
    reopened = Session.open(s.folder)
    assert reopened.model.journal_seq == s.model.journal_seq
    reopened.close()


def test_keyboard_shim_blocks_every_viser_camera_key():
    from app.ui.hotkeys import CAMERA_KEYS, KEYBOARD_SHIM

    assert KEYBOARD_SHIM.startswith("<img") and 'onerror="' in KEYBOARD_SHIM
    assert all(f"&quot;{code}&quot;" in KEYBOARD_SHIM for code in CAMERA_KEYS)
    assert len(CAMERA_KEYS) == 10 and '"' not in KEYBOARD_SHIM.split('onerror="')[1][:-2]


def test_accept_guesses_is_one_undoable_batch(session):
    st = AnnotateState(session, "browser-1")
    st.place_2d(np.array([150.0, 130.0]))  # joint 0 placed: its guess is ignored
    guesses = CAM.backproject(np.tile([[160.0, 120.0]], (21, 1)), np.full(21, 400.0))
    guesses[0] = CAM.backproject(np.array([10.0, 10.0]), np.float64(400.0))
    guesses[3] = np.nan  # no guess
    guesses[4] = CAM.backproject(np.array([-50.0, 10.0]), np.float64(400.0))  # off the image
    entry = st.accept_guesses(guesses)
    assert entry.command["kind"] == "batch"
    placed = [c["joint"] for c in entry.command["commands"]]
    assert placed == [j for j in range(21) if j not in (0, 3, 4)]
    ann = session.annotation(0)
    np.testing.assert_allclose(ann.uv_px[0], [150.0, 130.0])
    np.testing.assert_allclose(ann.uv_px[5], [160.0, 120.0], atol=0.01)
    assert st.joint == 3  # the first joint still to place
    assert ann.accepted.tolist() == [j not in (0, 3, 4) for j in range(21)]  # the click is not
    st.place_2d(np.array([158.0, 121.0]), joint=5, advance=False)  # a drag: no longer a guess
    assert not session.annotation(0).accepted[5]
    st.undo()
    ann = session.annotation(0)
    assert ann.accepted[5] and np.allclose(ann.uv_px[5], [160.0, 120.0], atol=0.01)
    st.undo()  # one step removes every accepted guess, keeps the click
    ann = session.annotation(0)
    assert ann.annotated.tolist() == [True] + [False] * 20
    assert st.accept_guesses(np.full((21, 3), np.nan)) is None


# ------------------------------------------------------------------ CLI help and defaults
def test_cli_every_option_has_help_and_select_defaults_to_5_percent(monkeypatch, tmp_path):
    import argparse

    from app import cli
    from handanno_core import pipeline

    parser = cli.build_parser()
    assert "workflow" in parser.format_help() and "handanno select" in parser.format_help()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for name, p in sub.choices.items():
        for action in p._actions:
            if action.help is argparse.SUPPRESS or isinstance(action, argparse._HelpAction):
                continue
            assert action.help, f"handanno {name} {action.option_strings or action.dest}: no help"
    assert "(default: 8080)" in sub.choices["serve"].format_help()

    s = make_session(tmp_path)
    s.close()
    seen = {}

    def fake_select(session, strategy, ref_fraction, rho, workers=1):
        seen.update(strategy=strategy, ref_fraction=ref_fraction, rho=rho)
        return SimpleNamespace(reference_frames=[0])

    monkeypatch.setattr(pipeline, "select", fake_select)
    # --sessions-dir is accepted after the command as well
    assert cli.main(["select", "sess", "--sessions-dir", str(tmp_path)]) == 0
    assert seen == {"strategy": "uniform", "ref_fraction": 0.05, "rho": None}
    assert cli.main(["--sessions-dir", str(tmp_path), "select", "sess", "--rho", "0.3"]) == 0
    assert seen["ref_fraction"] is None and seen["rho"] == 0.3


def test_worker_fits_guesses_with_the_frames_hand_model(session, monkeypatch):
    """The live refits pass the frame's hand model and points (asked once, at the frame's first
    lift) to the guesses' model fit, whose result is what the worker shows."""
    import handanno_core.guesses as guesses

    asked, fitted = [], []

    def guess_model(frame):
        asked.append(frame)
        return {"hand_model": "model", "observation": f"points of {frame}"}

    def model_guesses(joints, annotation, hand_model, observation, camera, weights=None):
        fitted.append((hand_model, observation))
        return joints + 1.0

    monkeypatch.setattr(guesses, "model_guesses", model_guesses)
    worker = LiftWorker(
        session, FrameStore(session), lift_fn=fake_lift, guess_model=guess_model
    ).start()
    try:
        place_and_lift(AnnotateState(session, "c"), worker, 2)
        assert asked == [0] and fitted == [("model", "points of 0")] * 2
        plain = fake_lift(session.annotation(0), None, session.camera, session.skeleton, None)
        np.testing.assert_allclose(worker.latest[0].joints_mm, plain.joints_mm + 1.0)
    finally:
        worker.stop()
