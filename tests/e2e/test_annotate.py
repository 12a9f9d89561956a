"""End-to-end: the annotation view in real Chromium, every step asserted on the session files.

One in-process server per module (on a free port) over a 40-frame 320x240 synthetic session.
The browser camera is set by the server to the depth sensor's pose ("Sensor view"), and click
targets are projected through the browser's own camera (viser_helpers.screen_of). Before a
gesture the scene is settled (:meth:`Ctx.settle`: every edit's lift drawn, the browser showing
what the server has); every wait is on a state (journal on disk, server view, page text).

``pytest tests/e2e --screenshots static/screenshots`` also writes the README screenshot.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from viser_helpers import (
    browser,
    click_gesture,
    close_notifications,
    dismiss_webgl_toast,
    drag_gesture,
    drawn,
    free_port,
    journal,
    notifications_seen,
    open_app,
    readme_screenshot,
    screen_of,
    settle_app,
    wait_for_node,
    wait_notification,
    wait_until,
)

from app.ui.server import AnnoServer, serve
from handanno_core.session import Session


def reopen(folder: Path) -> Session:
    """The session as a restarted server would see it (snapshot + journal replay); read-only use."""
    return Session.open(folder)


@dataclass
class Ctx:
    app: AnnoServer
    page: object
    folder: Path

    @property
    def view(self):
        views = self.app.annotate_panels()
        assert len(views) == 1, f"expected one connected browser, got {len(views)}"
        return views[0]

    def settle(self) -> None:
        """Wait until the scene holds still (:func:`settle_app`)."""
        settle_app(self.page, self.app)

    def image_point(self, uv) -> tuple[float, float]:
        """Page position of depth-image pixel ``uv`` (on the image plane)."""
        geo = self.view.frame_data.geometry
        return screen_of(self.page, "/hand", geo.pixel_to_scene(np.asarray(uv, float)))

    def joint_point(self, k: int) -> tuple[float, float]:
        """Page position of joint ``k``'s sphere where the browser draws it."""
        return screen_of(
            self.page, "/hand/joints", drawn(self.page, "/hand/joints")["instances"][k]
        )

    def click_image(self, uv) -> None:
        click_gesture(self.page, lambda: self.image_point(uv), settle=self.settle)


@pytest.fixture(scope="module")
def ctx(session_folder):
    app = serve(session_folder, port=free_port(), block=False)
    try:
        with browser() as b:
            page = open_app(b, app.url)
            wait_until(lambda: app.annotate_panels(), what="the view of the browser")
            ctx = Ctx(app, page, session_folder)
            ctx.settle()
            yield ctx
    finally:
        app.stop()


def hand_pixels(ctx: Ctx) -> tuple[np.ndarray, np.ndarray]:
    """Two pixels on the hand: its centre and one 25 px to the side that has depth."""
    geo = ctx.view.frame_data.geometry
    cam = ctx.app.session.camera
    centre = cam.project(geo.centre_mm)
    depth = ctx.view.frame_data.depth
    for du in (25, -25, 0):
        for dv in (0, 20, -20):
            uv = np.round(centre + (du, dv))
            if (du or dv) and depth[int(uv[1]), int(uv[0])] > 0:
                return np.round(centre), uv
    raise AssertionError("no second hand pixel found")


def _ring_band(ctx: Ctx, joint: int) -> tuple[float, float]:
    """Screen point on the band of ``joint``'s 2D ring, on the side away from its joint sphere."""
    page, view = ctx.page, ctx.view
    ring = drawn(page, "/hand/handles2d")["instances"][joint]
    centre = np.asarray(screen_of(page, "/hand/handles2d", ring))
    outer_m = float(view.hand.handles2d.batched_scales[joint])
    edge = screen_of(page, "/hand/handles2d", ring + [outer_m, 0, 0])
    outer = np.linalg.norm(np.asarray(edge) - centre)
    away = centre - np.asarray(ctx.joint_point(joint))
    away = away / np.linalg.norm(away) if np.linalg.norm(away) > 1 else np.array([1.0, 0.0])
    return tuple(centre + 0.85 * outer * away)


def _undo_redo_by_hotkeys(ctx: Ctx, frame: int) -> None:
    """Ctrl+Z undoes the last edit (joint 0 visible again, journaled as undo); Ctrl+Shift+Z
    redoes it."""
    page, folder = ctx.page, ctx.folder
    ctx.settle()
    page.evaluate("() => document.activeElement && document.activeElement.blur()")
    n = len(journal(folder))
    page.keyboard.press("Control+z")
    wait_until(
        lambda: len(journal(folder)) > n and journal(folder)[-1]["action"] == "undo",
        what="an undo entry",
    )
    assert reopen(folder).annotation(frame).visible[0]
    page.keyboard.press("Control+Shift+z")
    wait_until(lambda: journal(folder)[-1]["action"] == "redo", what="a redo entry")
    assert not reopen(folder).annotation(frame).visible[0]


def test_annotate_flow(ctx: Ctx):
    page, folder, view = ctx.page, ctx.folder, ctx.view
    frame = view.frame
    assert frame == 0 and view.state.joint == 0
    wait_until(page.get_by_text("0 of 4 reference frames annotated").is_visible, what="progress")

    # 1. Click on the depth image: the selected joint (wrist) gets that 2D position, joint 1 is next.
    uv0, uv1 = hand_pixels(ctx)
    ctx.click_image(uv0)
    entries = wait_until(
        lambda: [e for e in journal(folder) if e["command"]["kind"] == "set_2d"],
        what="a 2D edit in the journal",
    )
    cmd = entries[-1]["command"]
    assert (cmd["frame"], cmd["joint"]) == (frame, 0)
    assert np.allclose(cmd["uv_px"], uv0, atol=1.5), (cmd["uv_px"], uv0)
    wait_until(lambda: view.state.joint == 1, what="auto-advance to joint 1")
    ctx.click_image(uv1)
    wait_until(
        lambda: len([e for e in journal(folder) if e["command"]["kind"] == "set_2d"]) == 2,
        what="second 2D edit",
    )
    ann = reopen(folder).annotation(frame)
    assert np.allclose(ann.uv_px[0], uv0, atol=1.5) and np.allclose(ann.uv_px[1], uv1, atol=1.5)
    saved = page.get_by_text(re.compile(r"✓ saved \d\d:\d\d:\d\d \(edit #2\)"))
    wait_until(saved.is_visible, what="the saved indicator")

    # 1b. Drag joint 1's 2D ring by its band, on the side away from the joint sphere in front of
    # it (these two clicks are no hand, so the lift does not reproject exactly onto them), 25 px
    # to the right: the 2D position moves by the drag, not to the point where the ring was grabbed.
    ctx.settle()  # the lift moves the joint spheres in front of the rings
    screen_per_px = ctx.image_point(uv1 + (10.0, 0.0))[0] - ctx.image_point(uv1)[0]
    drag_gesture(page, lambda: _ring_band(ctx, 1), (25, 0), settle=ctx.settle)
    wait_until(
        lambda: len([e for e in journal(folder) if e["command"]["kind"] == "set_2d"]) == 3,
        what="a 2D ring drag edit",
    )
    cmd = journal(folder)[-1]["command"]
    assert (cmd["frame"], cmd["joint"]) == (frame, 1)
    expected = uv1 + (25.0 * 10.0 / screen_per_px, 0.0)
    assert np.allclose(cmd["uv_px"], expected, atol=1.5), (cmd["uv_px"], expected)

    # 2. Drag the wrist's 3D handle 60 px to the right: a 3D placement of joint 0 to the right.
    before = {}

    def settle_and_remember() -> None:
        ctx.settle()  # the lift moves the joint spheres
        before["xyz"] = view.joint_positions_mm()[0].copy()

    drag_gesture(page, lambda: ctx.joint_point(0), (60, 0), settle=settle_and_remember)
    entries = wait_until(
        lambda: [e for e in journal(folder) if e["command"]["kind"] == "set_3d"],
        what="a 3D drag edit",
    )
    cmd = entries[-1]["command"]
    assert (cmd["frame"], cmd["joint"]) == (frame, 0)
    moved = np.asarray(cmd["xyz_mm"]) - before["xyz"]
    assert moved[0] > 10.0, f"dragged right but x moved {moved}"
    ann = reopen(folder).annotation(frame)
    assert np.allclose(ann.xyz_mm[0], cmd["xyz_mm"], atol=0.01)
    assert view.state.joint == 0  # a drag selects the dragged joint, no auto-advance

    # 3. Toggle visibility of the selected joint with the panel button.
    page.get_by_role("button", name="Visibility: visible (V)").click()
    wait_until(
        lambda: journal(folder)[-1]["command"]["kind"] == "set_visible", what="a visibility edit"
    )
    assert journal(folder)[-1]["command"] == {
        "frame": frame,
        "kind": "set_visible",
        "joint": 0,
        "visible": False,
    }
    assert not reopen(folder).annotation(frame).visible[0]
    wait_until(
        lambda: page.get_by_role("button", name="Visibility: occluded (V)").is_visible(),
        what="button label",
    )

    # 4. Undo with Ctrl+Z (hotkey through viser's command layer): visibility is back, journaled as undo.
    _undo_redo_by_hotkeys(ctx, frame)

    # 5. Next frame by hotkey N: the view moves to the next reference frame.
    page.evaluate("() => document.activeElement && document.activeElement.blur()")
    page.keyboard.press("n")
    wait_until(lambda: view.frame == 10, what="next reference frame")
    wait_until(
        lambda: page.get_by_text("Frame 10", exact=True).is_visible(),
        what="the panel showing frame 10",
    )
    ctx.settle()


def test_other_client_edit_refreshes_and_screenshot(ctx: Ctx, tmp_path):
    """An edit by another client on the frame shown is drawn (and lifted); README screenshot
    (into tmp_path; into static/screenshots only with ``--screenshots``)."""
    from handanno_core.synth import simulate_annotation

    app, view = ctx.app, ctx.view
    session = app.session
    frame = view.frame
    seq = session.open_sequence()
    ann = simulate_annotation(
        seq.ground_truth.joints_mm[frame], seq.depth(frame), session.camera, session.skeleton
    )
    from handanno_core.session import SetFrameAnnotation

    shown = len(notifications_seen(ctx.page))
    entry = session.execute(
        SetFrameAnnotation(frame=frame, annotation=ann.to_json()), client="another-annotator"
    )
    wait_notification(
        ctx.page,
        "Frame edited elsewhere",
        f"another annotator changed frame {frame}",
        since=shown,
    )
    # issue 16: the notice never shows the other browser's journal id
    assert all("another-annotator" not in n["message"] for n in notifications_seen(ctx.page))
    wait_until(
        lambda: view.last_skeleton_update is not None and view.last_skeleton_update[0] >= entry.seq,
        what="the lifted skeleton",
    )
    assert np.allclose(view._annotation.uv_px, ann.uv_px, atol=1e-3, equal_nan=True)
    gt = seq.ground_truth.joints_mm[frame]
    err = np.linalg.norm(view._lifted.joints_mm - gt, axis=1)
    assert np.median(err) < 15.0, f"lifted skeleton far from ground truth: {err}"
    view.hand.reset_camera()  # as the "Sensor view" button does
    ctx.settle()
    close_notifications(ctx.page)
    shot = readme_screenshot(ctx.page, "annotate.png", tmp_path)
    assert shot.stat().st_size > 10_000


def test_frame_without_depth_shows_message(ctx: Ctx, monkeypatch):
    """A frame whose depth cannot be read shows a message in the page; the view keeps working."""
    from app.control.frames import FrameData
    from app.control.geometry import empty_geometry

    app, view, page = ctx.app, ctx.view, ctx.page
    real_get = app.frames.get

    def get(frame: int) -> FrameData:
        if frame == 20:
            msg = "frame 20: no depth (000020_depth.bin: truncated)"
            return FrameData(20, None, empty_geometry(app.session.camera), error=msg)
        return real_get(frame)

    monkeypatch.setattr(app.frames, "get", get)
    view.go_to_index(view.state.frames.index(20))
    view.flush()
    wait_until(lambda: page.get_by_text("⚠ frame 20: no depth").is_visible(), what="the message")
    # the lift status is about the shown frame (or empty), never the previous frame's lift
    lift_text = view.w.lift_md.content
    assert lift_text == "" or "frame 20" in lift_text, lift_text
    assert (
        view.clicks.on_image_click(
            view.frame_data.geometry.sensor_position, np.array([0.0, 0.0, 1.0])
        )
        is None
    )
    view.go_to_index(view.state.frames.index(30))  # and the next frame is fine again
    wait_until(
        lambda: not page.get_by_text("⚠ frame 20: no depth").is_visible(), what="message gone"
    )
    assert view.frame_data.depth is not None


def test_undo_survives_a_page_reload(ctx: Ctx):
    """Edits carry a per-browser name kept in localStorage, so after a reload Ctrl+Z still undoes
    the edit made before it (the session rebuilds undo stacks per name from the journal)."""
    page, folder = ctx.page, ctx.folder
    old = ctx.view
    ctx.settle()
    page.evaluate("() => document.activeElement && document.activeElement.blur()")
    n = len(journal(folder))
    page.keyboard.press("v")
    wait_until(lambda: len(journal(folder)) > n, what="the visibility edit")
    edit = journal(folder)[-1]
    assert edit["command"]["kind"] == "set_visible" and edit["client"].startswith("browser-")
    page.reload()
    wait_for_node(page, "/hand/joints")
    dismiss_webgl_toast(page)
    wait_until(
        lambda: (views := ctx.app.annotate_panels()) and views[0] is not old and len(views) == 1,
        what="the reloaded page's view",
    )
    new = ctx.view
    assert new.state.client == edit["client"]
    # the reloaded page says its earlier edits are saved (not "no edits yet")
    wait_until(lambda: "undo available" in new.w.saved_md.content, what="the saved status")
    ctx.settle()  # the page has the new view's hotkey bindings
    page.evaluate("() => document.activeElement && document.activeElement.blur()")
    page.keyboard.press("Control+z")
    wait_until(lambda: journal(folder)[-1]["action"] == "undo", what="an undo after the reload")
    undo = journal(folder)[-1]
    assert undo["target"] == edit["seq"] and undo["client"] == edit["client"]


def test_a_joint_past_the_border_is_marked_outside_the_image_by_its_hotkey(ctx: Ctx):
    """A hand past the image's border: the annotator presses O on the selected joint. The journal
    holds the mark, the next joint is selected, the panel's button says so for the marked joint
    (selected again), and O again takes the mark away."""
    page, folder, view = ctx.page, ctx.folder, ctx.view
    ctx.settle()
    frame, joint = view.frame, view.state.joint
    page.evaluate("() => document.activeElement && document.activeElement.blur()")
    n = len(journal(folder))
    page.keyboard.press("o")
    wait_until(lambda: len(journal(folder)) > n, what="the outside-the-image mark")
    entry = journal(folder)[-1]
    assert entry["command"] == {
        "kind": "set_outside", "frame": frame, "joint": joint, "outside": True
    }  # fmt: skip
    ann = reopen(folder).annotation(frame)
    assert ann.outside[joint] and not ann.annotated[joint]
    # the next unplaced joint is selected (by the app's thread, after the journal entry is written)
    wait_until(lambda: view.state.joint != joint, what="the next joint selected")
    view.select_joint(joint)
    wait_until(
        lambda: page.get_by_role("button", name="Outside the image: yes (O)").is_visible(),
        what="the button showing the mark",
    )
    ctx.settle()
    page.evaluate("() => document.activeElement && document.activeElement.blur()")
    page.keyboard.press("o")
    wait_until(lambda: len(journal(folder)) > n + 1, what="the mark taken away")
    assert not reopen(folder).annotation(frame).outside[joint]
    wait_until(
        lambda: page.get_by_role("button", name="Outside the image (O)").is_visible(),
        what="the button without the mark",
    )
