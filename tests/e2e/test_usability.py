"""End-to-end: the annotation app as a new annotator finds it (issue 15), in real Chromium, every
check asserted on the session's files (journal.jsonl, results.npz) or on the server's state.

One in-process server per module on a free port, over the 40-frame synthetic session of
conftest.py (references 0, 10, 20, 30). The live lift is a stand-in that returns the frame's
ground-truth joints, so the guesses of unplaced joints sit exactly where the annotator will click
(the hardest case for "guesses never swallow clicks"); *Propagate & refine* runs the real lift,
propagation and refinement. The tests run in file order on one page: each one leaves the view on
its own reference frame.

``HANDANNO_SCREENSHOTS=DIR`` also writes the README screenshots (annotate, review) to DIR.
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from conftest import make_session
from viser_helpers import (
    browser,
    camera_state,
    free_port,
    journal,
    open_app,
    screen_of,
    wait_camera_still,
    wait_until,
)

from app.ui.server import AnnoServer, serve

REPO = Path(__file__).resolve().parents[2]
THUMB_IP, THUMB_TIP = 19, 20


class GroundTruthLift:
    """Stand-in for the live lift: the ground-truth joints of the frame whose depth it is given."""

    def __init__(self, sequence):
        self.gt = sequence.ground_truth.joints_mm
        self.frame_of = {self._key(sequence.depth(f)): f for f in range(len(self.gt))}

    @staticmethod
    def _key(depth) -> str:
        return hashlib.sha1(np.ascontiguousarray(depth, dtype=np.float32).tobytes()).hexdigest()

    def __call__(self, annotation, depth, camera, skeleton, bones, **_):
        joints = self.gt[self.frame_of[self._key(depth)]].astype(np.float64)
        return SimpleNamespace(joints_mm=joints, confidence=np.ones(len(joints)))


@dataclass
class Ctx:
    app: AnnoServer
    page: object
    folder: Path
    gt_mm: np.ndarray  # (N, J, 3) ground truth of every frame

    @property
    def view(self):
        views = self.app.annotate_panels()
        assert len(views) == 1, f"expected one connected browser, got {len(views)}"
        return views[0]

    def gt_uv(self, frame: int) -> np.ndarray:
        """(J, 2) ground-truth pixel of every joint of ``frame``."""
        return self.app.session.camera.project(self.gt_mm[frame])

    def image_point(self, uv) -> tuple[float, float]:
        """Page position of depth-image pixel ``uv`` (on the image plane)."""
        geo = self.view.frame_data.geometry
        return screen_of(self.page, "/hand", geo.pixel_to_scene(np.asarray(uv, float)))

    def drawn_point(self, node: str, k: int) -> tuple[float, float]:
        """Page position of joint ``k`` as drawn in ``node`` (joints or guesses)."""
        return screen_of(self.page, node, self.view.joint_positions_scene()[k])

    def edits(self, kind: str | None = None, since: int = 0) -> list[dict]:
        """Journal entries after index ``since`` (of one command kind)."""
        out = journal(self.folder)[since:]
        return [e for e in out if kind is None or e["command"]["kind"] == kind]

    def blur(self) -> None:
        self.page.evaluate("() => document.activeElement && document.activeElement.blur()")

    def frames_rendered(self, n: int = 30) -> None:
        """Wait until the page has drawn ``n`` more animation frames (keys held meanwhile)."""
        self.page.evaluate(
            """(n) => new Promise((done) => {
                let k = 0;
                const step = () => (++k >= n ? done() : requestAnimationFrame(step));
                requestAnimationFrame(step);
            })""",
            n,
        )

    def drag(self, start: tuple[float, float], end: tuple[float, float], steps: int = 4) -> None:
        """A mouse drag that lets the page draw between its moves (a loaded machine otherwise
        coalesces the moves before viser's drag threshold is seen)."""
        page = self.page
        page.mouse.move(*start)
        page.mouse.down()
        self.frames_rendered(2)
        for t in np.linspace(0.0, 1.0, steps + 1)[1:]:
            page.mouse.move(start[0] + t * (end[0] - start[0]), start[1] + t * (end[1] - start[1]))
            self.frames_rendered(1)
        page.mouse.up()

    def go_to(self, frame: int) -> None:
        """Next reference frame with the N hotkey until ``frame`` is shown, in sensor view."""
        view = self.view
        while view.frame < frame:
            target = view.state.frames[view.state.index + 1]
            self.blur()
            self.page.keyboard.press("n")
            wait_until(lambda t=target: view.frame == t, what=f"frame {target}")
        view.flush()
        wait_camera_still(self.page)


@pytest.fixture(scope="module")
def ctx(session_folder):
    from handanno_core.session import Session

    with Session.open(session_folder) as session:
        sequence = session.open_sequence()
        gt = np.asarray(sequence.ground_truth.joints_mm, dtype=np.float64)
        lift = GroundTruthLift(sequence)
    app = serve(session_folder, port=free_port(), block=False, lift_fn=lift)
    app.session.model.settings.aligner = "dis"  # the fast aligner keeps the module in budget
    try:
        with browser() as b:
            page = open_app(b, app.url)
            wait_until(lambda: app.annotate_panels(), what="the view of the browser")
            app.annotate_panels()[0].flush()
            wait_camera_still(page)
            yield Ctx(app, page, session_folder, gt)
    finally:
        app.stop()


def screenshot(ctx: Ctx, name: str) -> None:
    """README screenshots, only when HANDANNO_SCREENSHOTS=DIR is set (never in normal runs)."""
    out = os.environ.get("HANDANNO_SCREENSHOTS")
    if out:
        Path(out).mkdir(parents=True, exist_ok=True)
        ctx.page.screenshot(path=str(Path(out) / name))


def annotate_by_clicks(ctx: Ctx, frame: int) -> list[dict]:
    """Click the ground-truth pixel of every joint of ``frame`` in order (2D mode, auto-advance);
    from the second joint on, each click lands exactly on that joint's drawn guess. Returns the
    21 set_2d journal entries."""
    view, page = ctx.view, ctx.page
    assert view.frame == frame and view.state.click_mode == "2d"
    uv = ctx.gt_uv(frame)
    start = len(journal(ctx.folder))
    for k in range(view.skeleton.num_joints):
        wait_until(lambda k=k: view.state.joint == k, what=f"joint {k} selected")
        target = ctx.image_point(uv[k])
        if k > 0:
            # the live lift's guess of joint k is drawn (small, not clickable) right there
            wait_until(
                lambda k=k: (
                    view.hand.guesses.batched_scales[k] > 0 and not view._annotation.has_2d[k]
                ),
                what=f"the guess of joint {k}",
            )
            view.flush()
            assert np.allclose(ctx.drawn_point("/hand/guesses", k), target, atol=1.0)
        page.mouse.click(*target)
        wait_until(
            lambda k=k: len(ctx.edits("set_2d", since=start)) == k + 1,
            what=f"the 2D edit of joint {k}",
        )
    return ctx.edits("set_2d", since=start)


def test_clicks_on_guessed_joints_place_the_selected_joint(ctx: Ctx):
    """Issue 15 item 2: 21 clicks on the ground-truth pixels, each on its own joint's guess (and
    often on a placed neighbour's sphere or ring), give 21 edits of the right joints."""
    view = ctx.view
    frame = view.frame
    assert frame == 0
    entries = annotate_by_clicks(ctx, frame)
    assert [e["command"]["joint"] for e in entries] == list(range(21))
    assert all(e["command"]["frame"] == frame for e in entries)
    uv = np.array([e["command"]["uv_px"] for e in entries])
    err = np.linalg.norm(uv - ctx.gt_uv(frame), axis=1)
    assert err.max() < 1.5, f"2D placements off the clicked pixels by {err.max():.2f} px"
    # guesses look different from placed joints: smaller, and faded
    wait_until(lambda: not np.any(view.hand.guesses.batched_scales), what="no guess left")
    assert np.all(view.hand.joints.batched_scales > 0)  # every joint placed
    assert float(np.max(view.hand.guesses.batched_opacities)) < 0.5
    screenshot(ctx, "annotate.png")


@pytest.mark.slow  # the real lift, propagation and refinement (about 20 s)
def test_propagate_and_refine_on_a_browser_annotated_session(ctx: Ctx):
    """Issue 15 item 1: no `handanno lift`: *Propagate & refine* lifts the references and estimates
    the bone lengths itself, then propagates and refines; results.npz has the final joints."""
    app, page, folder = ctx.app, ctx.page, ctx.folder
    if not app.session.is_annotated(0):  # run alone: annotate frame 0 through the page first
        annotate_by_clicks(ctx, 0)
    assert app.session.model.bone_lengths_mm is None
    page.get_by_role("tab", name="Review").click()
    page.get_by_role("button", name="Propagate & refine").click()
    runner = app.ctx.runner
    wait_until(
        lambda: (
            runner.status.phase in ("done", "failed", "cancelled") and not runner.status.running
        ),
        timeout_s=240,
        what="the propagate & refine run",
    )
    assert runner.status.phase == "done", runner.status.message
    assert any(h.phase == "done" for h in runner.history)
    with np.load(folder / "results.npz") as results:
        final = results["final_mm"]
        lifted = results["lifted_mm"]
    subtree = np.arange(10)  # reference 0 and the frames propagated from it
    assert np.all(np.isfinite(final[subtree])), "frames 0-9 have no final joints on disk"
    assert np.all(np.isfinite(lifted[0]))
    assert app.session.model.bone_lengths_mm is not None
    err = np.linalg.norm(final[subtree] - ctx.gt_mm[subtree], axis=-1)
    assert np.median(err) < 20.0, f"median error {np.median(err):.1f} mm"
    page.get_by_text("done: ").first.wait_for(timeout=10_000)
    screenshot(ctx, "review.png")
    # review hotkeys on the Review scene: W next worst, A accept (and advance), N next frame
    (review,) = app.review_panels()
    wait_until(lambda: review.scene_active, what="the review scene")
    ctx.blur()
    shown = review.frame
    page.keyboard.press("w")
    wait_until(lambda: review.frame != shown, what="the next worst frame")
    worst, start = review.frame, len(journal(folder))
    page.keyboard.press("a")
    entries = wait_until(lambda: ctx.edits("set_review", since=start), what="the accept")
    assert entries[0]["command"] == {"frame": worst, "kind": "set_review", "status": "accepted"}
    wait_until(lambda: review.frame != worst, what="accept moving on")
    shown = review.frame
    # N steps to the next frame, P to the previous one (whichever exists from the shown frame)
    key, step = ("n", 1) if shown + 1 < app.session.num_frames else ("p", -1)
    page.keyboard.press(key)
    wait_until(lambda: review.frame == shown + step, what=f"the frame after '{key}'")
    # back to the annotate scene and tab for the next tests
    page.get_by_role("button", name="Show annotate scene").click()
    page.get_by_role("tab", name="Annotate").click()
    wait_until(lambda: not review.scene_active, what="the annotate scene back")


def test_3d_mode_click_on_a_sphere_selects_and_never_moves_it(ctx: Ctx):
    """Issue 15 item 3: in *3D on cloud* mode, with thumb_tip selected, a click on thumb_ip's sphere
    selects thumb_ip and journals nothing; a click on the cloud then places thumb_ip; dragging a
    joint that is not selected only selects it, dragging the selected one moves it."""
    from handanno_core.session import SetFrameAnnotation
    from handanno_core.synth import simulate_annotation

    app, page, view = ctx.app, ctx.page, ctx.view
    frame = 10
    session = app.session
    depth = np.asarray(session.open_sequence().depth(frame), dtype=np.float32)
    ann = simulate_annotation(ctx.gt_mm[frame], depth, session.camera, session.skeleton)
    session.execute(SetFrameAnnotation(frame=frame, annotation=ann.to_json()), client="setup")
    ctx.go_to(frame)
    wait_until(lambda: view._lifted is not None, what="the lifted skeleton")
    view.flush()
    ctx.blur()
    page.keyboard.press("m")
    wait_until(lambda: view.state.click_mode == "3d", what="3D click mode")
    page.keyboard.press("ArrowLeft")  # joint 0 -> 20 (wraps)
    wait_until(lambda: view.state.joint == THUMB_TIP, what="thumb_tip selected")
    view.flush()

    start = len(journal(ctx.folder))
    page.mouse.click(*ctx.drawn_point("/hand/joints", THUMB_IP))
    wait_until(lambda: view.state.joint == THUMB_IP, what="thumb_ip selected by its click")
    page.keyboard.press("v")  # an edit on the selected joint: proves the order of events
    wait_until(lambda: ctx.edits(since=start), what="the visibility edit")
    assert [e["command"]["kind"] for e in ctx.edits(since=start)] == ["set_visible"]
    assert ctx.edits(since=start)[0]["command"]["joint"] == THUMB_IP

    # a click on the cloud away from every sphere places the selected joint (thumb_ip) there
    uv, xyz = cloud_pixel_away_from_joints(ctx, frame, depth)
    start = len(journal(ctx.folder))
    page.mouse.click(*ctx.image_point(uv))
    entries = wait_until(lambda: ctx.edits("set_3d", since=start), what="a 3D placement")
    cmd = entries[0]["command"]
    assert cmd["joint"] == THUMB_IP and cmd["frame"] == frame
    assert np.linalg.norm(np.asarray(cmd["xyz_mm"]) - xyz) < 10.0, (cmd["xyz_mm"], xyz)

    # dragging the wrist (not selected) selects it without moving it ...
    wait_until(lambda: app.worker.wait_idle(1) and view._stale == {}, what="the re-lift")
    view.flush()
    start = len(journal(ctx.folder))
    p0 = ctx.drawn_point("/hand/joints", 0)
    ctx.drag(p0, (p0[0] + 60, p0[1]))
    wait_until(lambda: view.state.joint == 0, what="the wrist selected by the drag")
    page.keyboard.press("v")
    wait_until(lambda: ctx.edits(since=start), what="the visibility edit")
    assert [e["command"]["kind"] for e in ctx.edits(since=start)] == ["set_visible"]
    # ... and dragging it again, now selected, moves it
    view.flush()
    start = len(journal(ctx.folder))
    p0 = ctx.drawn_point("/hand/joints", 0)
    ctx.drag(p0, (p0[0] + 60, p0[1]))
    entries = wait_until(lambda: ctx.edits("set_3d", since=start), what="the wrist drag")
    assert entries[0]["command"]["joint"] == 0
    page.keyboard.press("m")
    wait_until(lambda: view.state.click_mode == "2d", what="2D click mode again")


def cloud_pixel_away_from_joints(ctx: Ctx, frame: int, depth: np.ndarray):
    """A hand pixel (with depth) as far as possible from every drawn joint, and its 3D point."""
    cam = ctx.app.session.camera
    joints_uv = cam.project(ctx.view.hand.display_mm(ctx.view.joint_positions_mm()))
    centre = joints_uv.mean(axis=0)
    rows, cols = np.nonzero(depth > 0)
    uv = np.stack([cols, rows], axis=1).astype(np.float64)
    near = np.linalg.norm(uv - centre, axis=1) < 60
    uv = uv[near]
    gap = np.min(np.linalg.norm(uv[:, None] - joints_uv[None], axis=2), axis=1)
    best = uv[np.argmax(gap)]
    assert gap.max() > 6.0, "no hand pixel away from the joints"
    z = depth[int(best[1]), int(best[0])]
    return best, cam.backproject(best[None], np.array([z]))[0]


def test_hotkeys_never_move_the_camera(ctx: Ctx):
    """Issue 15 item 4: holding D (depth order) and the arrow keys (joint selection) edits and
    selects, and leaves the camera pose unchanged in the browser and on the server."""
    page, view = ctx.page, ctx.view
    ctx.blur()
    wait_camera_still(page)
    client_cam = view.client.camera
    before_page = camera_state(page)
    before_server = (client_cam.position.copy(), client_cam.wxyz.copy())
    if view.state.joint == 0:
        page.keyboard.press("ArrowRight")
        wait_until(lambda: view.state.joint == 1, what="joint 1 selected")
    joint = view.state.joint

    start = len(journal(ctx.folder))
    page.keyboard.down("d")
    wait_until(lambda: ctx.edits("set_depth_order", since=start), what="the depth-order edit")
    ctx.frames_rendered()
    page.keyboard.up("d")
    assert ctx.edits("set_depth_order", since=start)[0]["command"]["joint"] == joint
    for key, expect in (("ArrowRight", joint + 1), ("ArrowLeft", joint), ("ArrowUp", None)):
        page.keyboard.down(key)
        if expect is not None:
            wait_until(lambda e=expect: view.state.joint == e, what=f"{key} selecting {expect}")
        ctx.frames_rendered()
        page.keyboard.up(key)
    ctx.frames_rendered()
    assert np.allclose(camera_state(page), before_page, atol=1e-6), "a hotkey moved the camera"
    # the server's copy of the browser camera: an edit after the keys is journaled, so every
    # camera message sent before it has arrived too
    start = len(journal(ctx.folder))
    page.keyboard.press("v")
    wait_until(lambda: ctx.edits(since=start), what="the visibility edit")
    assert np.allclose(client_cam.position, before_server[0], atol=1e-6)
    assert np.allclose(client_cam.wxyz, before_server[1], atol=1e-6)

    # typing in a number box, then Enter: the hotkeys work again (Enter leaves the box)
    box = page.locator("input[inputmode='numeric'], input[inputmode='decimal']").first
    box.click()
    box.press("End")
    box.press("Enter")
    assert page.evaluate("() => document.activeElement.tagName") != "INPUT"
    start = len(journal(ctx.folder))
    page.keyboard.press("v")
    wait_until(lambda: ctx.edits(since=start), what="a hotkey edit after the number box")
    # ... or without Enter, a press on the 3D scene leaves the box (viser's canvas keeps focus
    # where it is otherwise); a right-button press edits nothing
    box.click()
    box.press("End")
    assert page.evaluate("() => document.activeElement.tagName") == "INPUT"
    canvas = page.locator("canvas").first.bounding_box()
    page.mouse.click(canvas["x"] + 10, canvas["y"] + canvas["height"] - 10, button="right")
    assert page.evaluate("() => document.activeElement.tagName") != "INPUT"
    start = len(journal(ctx.folder))
    page.keyboard.press("v")
    wait_until(lambda: ctx.edits(since=start), what="a hotkey edit after a press on the scene")


def test_sensor_view_is_square_on(ctx: Ctx):
    """Issue 15: *Sensor view* looks along the depth camera's optical axis (the image plane is
    seen square-on, as the sensor sees it), from the sensor position."""
    page, view = ctx.page, ctx.view
    page.get_by_role("button", name="Sensor view").click()
    geo = view.frame_data.geometry
    cam = view.client.camera
    wait_until(
        lambda: np.allclose(cam.position, geo.sensor_position, atol=1e-4),
        what="the browser camera at the sensor",
    )
    wait_camera_still(page)
    forward = np.asarray(cam.look_at) - np.asarray(cam.position)
    assert np.allclose(forward / np.linalg.norm(forward), [0.0, 0.0, 1.0], atol=1e-3)


def test_undoing_every_joint_clears_the_skeleton(ctx: Ctx):
    """Issue 15 item 5: after undoing every joint of a frame no skeleton or guess is drawn, the
    selection is back on the first joint, and a click where a guess was places that joint."""
    page, view = ctx.page, ctx.view
    frame = 20
    ctx.go_to(frame)
    assert view.state.click_mode == "2d" and view.state.joint == 0
    uv = ctx.gt_uv(frame)
    start = len(journal(ctx.folder))
    for k in (0, 1):
        page.mouse.click(*ctx.image_point(uv[k]))
        wait_until(lambda k=k: len(ctx.edits("set_2d", since=start)) == k + 1, what="2D edit")
        wait_until(lambda k=k: view.state.joint == k + 1, what="auto-advance")
    wait_until(lambda: view.hand.guesses.batched_scales[5] > 0, what="the guessed skeleton")
    ctx.blur()
    for n in (1, 2):
        page.keyboard.press("Control+z")
        wait_until(
            lambda n=n: len([e for e in ctx.edits(since=start) if e["action"] == "undo"]) == n,
            what=f"undo {n}",
        )
    wait_until(
        lambda: (
            view._lifted is None
            and not np.any(view.hand.joints.batched_scales)
            and not np.any(view.hand.handles2d.batched_scales)
        ),
        what="the skeleton cleared",
    )
    assert view.state.joint == 0  # undo selected the undone joint
    view.flush()
    if view._prefill is None:
        assert not np.any(view.hand.guesses.batched_scales)
        assert not any(label.visible for label in view.hand.labels)
    else:  # what is left is the frame's pre-fill, as when it was opened: guesses only
        drawn = view.frame_data.geometry.to_scene(view.hand.display_mm(view._prefill))
        assert np.allclose(view.hand.guesses.batched_positions, drawn, atol=1e-4)
    start = len(journal(ctx.folder))
    page.mouse.click(*ctx.image_point(uv[5]))
    entries = wait_until(lambda: ctx.edits("set_2d", since=start), what="a 2D edit")
    cmd = entries[0]["command"]
    assert (cmd["frame"], cmd["joint"]) == (frame, 0)
    assert np.allclose(cmd["uv_px"], uv[5], atol=1.5)


def test_busy_port_is_an_error_naming_it(ctx: Ctx, synthetic_data, tmp_path):
    """Issue 15 item 6: `handanno serve` on a port in use exits with an error naming the port and
    serves nothing (no move to the next port); the running server keeps working."""
    other = make_session(tmp_path / "other", synthetic_data)
    port = ctx.app.port
    env = dict(os.environ, PYTHONPATH=str(REPO))
    proc = subprocess.run(
        [sys.executable, "-m", "app.cli", "serve", str(other), "--port", str(port)],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=REPO,
        env=env,
    )
    assert proc.returncode == 2, proc.stderr
    assert f"port {port}" in proc.stderr and "already in use" in proc.stderr, proc.stderr
    assert "annotate at" not in proc.stdout
    assert not (other / "journal.jsonl").exists()
    # the page still talks to the first server
    start = len(journal(ctx.folder))
    ctx.blur()
    ctx.page.keyboard.press("v")
    wait_until(lambda: ctx.edits(since=start), what="an edit on the first server")


def test_accept_guesses_places_the_prefill_in_one_undoable_edit(ctx: Ctx):
    """Issue 15 minor / issue 14: a reference opens with its pre-filled pose as guesses (from the
    nearest frame with joints); G accepts them as ONE journaled edit; Ctrl+Z undoes all of it."""
    app, page, view = ctx.app, ctx.page, ctx.view
    frame = 30
    if app.ctx.prefill(frame) is None:  # run alone: give the session one frame with joints
        lifted = app.session.load_results()["lifted_mm"]
        lifted[20] = ctx.gt_mm[20]
        app.session.save_results(lifted_mm=lifted)
    ctx.go_to(frame)
    wait_until(
        lambda: view._prefill is not None and np.all(view.hand.guesses.batched_scales > 0),
        timeout_s=60,
        what="the pre-filled guesses",
    )
    expected_uv = app.session.camera.project(view._prefill)
    err = np.linalg.norm(expected_uv - ctx.gt_uv(frame), axis=1)
    assert np.median(err) < 40.0, f"pre-fill far from the hand: {err}"  # hand-shaped, nearby
    start = len(journal(ctx.folder))
    ctx.blur()
    page.keyboard.press("g")
    entries = wait_until(lambda: ctx.edits(since=start), what="the accept edit")
    assert len(entries) == 1 and entries[0]["command"]["kind"] == "batch"
    cmds = entries[0]["command"]["commands"]
    assert [c["joint"] for c in cmds] == list(range(21))
    assert all(c["kind"] == "set_2d" and c["frame"] == frame for c in cmds)
    assert all(c["accepted"] for c in cmds)  # journaled as guesses, not clicks
    assert np.allclose([c["uv_px"] for c in cmds], expected_uv, atol=0.01)
    wait_until(lambda: app.session.is_annotated(frame), what="the frame annotated")
    page.keyboard.press("Control+z")
    wait_until(lambda: len(ctx.edits(since=start)) == 2, what="the undo")
    undo = ctx.edits(since=start)[1]
    assert undo["action"] == "undo" and undo["target"] == entries[0]["seq"]
    wait_until(lambda: not app.session.annotation(frame).annotated.any(), what="all undone")
