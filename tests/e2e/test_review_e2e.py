"""End-to-end: the Review tab in real Chromium (issue 8), every step checked on the session files.

One in-process server per module over the 40-frame synthetic sequence of conftest.py, with a
chained parent forest (references 0, 10, 20, 30; every other frame's parent is the frame before),
lifted references taken from ground truth and the DIS aligner, so the module stays fast on two
cores. Propagation is the real one, slowed per frame so that the page can be watched filling in.
Every wait is on a state (journal, runner, page text, what the browser draws); gestures settle
the scene first and retry a press that found no joint (viser_helpers.drag_gesture).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from review_session import STEP, build_review_session
from viser_helpers import (
    browser,
    drag_gesture,
    drawn,
    free_port,
    journal,
    notifications_seen,
    open_app,
    screen_of,
    sync_browser,
    wait_camera_still,
    wait_drawn,
    wait_notification,
    wait_until,
)

from app.control.review import ReviewState
from app.ui.server import AnnoServer, serve
from handanno_core.session import JOURNAL_FILE, Session


class FastLift:
    """Stand-in for lift_frame (the lift is tested in test_lift.py): the placed 3D joints."""

    def __call__(self, annotation, depth, camera, skeleton, bones, **_):
        """Placed 3D joints as they are; 2D-only joints back-projected 10 mm behind the surface."""
        from types import SimpleNamespace

        uv = np.nan_to_num(annotation.uv_px)
        col = np.clip(np.rint(uv[:, 0]).astype(int), 0, camera.width - 1)
        row = np.clip(np.rint(uv[:, 1]).astype(int), 0, camera.height - 1)
        d = depth[row, col].astype(np.float64)
        d = np.where(d > 0, d, np.median(d[d > 0]) if (d > 0).any() else 400.0) + 10.0
        x = camera.backproject(uv, d)
        placed = np.all(np.isfinite(annotation.xyz_mm), axis=1)
        x[placed] = annotation.xyz_mm[placed]
        # keep the bone lengths (directions as clicked), as every real lift does; placed joints stay
        lengths = dict(zip(skeleton.bones[:, 1].tolist(), np.asarray(bones).tolist(), strict=True))
        out = x.copy()
        for c in skeleton.topological_order[1:]:
            p = skeleton.parent_array[c]
            v = x[c] - x[p]
            if not placed[c]:
                out[c] = out[p] + v / max(np.linalg.norm(v), 1e-9) * lengths[int(c)]
        return SimpleNamespace(joints_mm=out, confidence=np.ones(len(x)))


def slowed_propagate(delay_s: float):
    from handanno_core.pipeline import propagate

    def run(session, **kw):
        on_result = kw.pop("on_result")

        def slow(frame, joints, conf):
            time.sleep(delay_s)
            on_result(frame, joints, conf)

        return propagate(session, on_result=slow, **kw)

    return run


@dataclass
class Ctx:
    app: AnnoServer
    browser: object
    page: object
    folder: Path
    #: one item per "finished" event of the runner, appended after the views re-rendered
    finished: list

    def view(self, index: int = 0):
        views = sorted(
            self.app.review_panels(),
            key=lambda v: v.client.client_id,
        )
        return views[index]

    def settle(self, page, view) -> None:
        """Wait until the review scene of ``page`` holds still: no job queued or running, the
        views re-rendered after the last one, the browser drawing what the server has."""
        runner = self.app.ctx.runner
        wait_until(
            lambda: runner.wait_idle(0.5) and len(self.finished) >= len(runner.history),
            what="the review runner to finish and the views to redraw",
        )
        sync_browser(page, view.client)
        wait_drawn(page, view.hand.joints)
        wait_camera_still(page)


@pytest.fixture(scope="module")
def ctx(synthetic_data, tmp_path_factory):
    folder = build_review_session(tmp_path_factory.mktemp("e2e-review") / "sess", synthetic_data)
    app = serve(
        folder,
        port=free_port(),
        block=False,
        lift_fn=FastLift(),
        review_options={"propagate_fn": slowed_propagate(0.12), "debounce_s": 0.3},
    )
    try:
        with browser() as b:
            page = open_app(b, app.url)
            wait_until(lambda: app.review_panels(), what="the review view")
            finished = []
            app.ctx.runner.listeners.append(
                lambda event, runner, frame: finished.append(frame) if event == "finished" else None
            )
            open_review_tab(page)
            yield Ctx(app, b, page, folder, finished)
    finally:
        app.stop()


def open_review_tab(page) -> None:
    page.get_by_role("tab", name="Review").click()
    page.get_by_role("button", name="Propagate & refine").wait_for(timeout=90_000)


def run_results(folder: Path, worker) -> dict[str, np.ndarray]:
    """The results a propagate & refine run writes: init_mm, final_mm, and the confidence of
    frames the app's lift worker never lifted (its idle-time save writes lifted_mm and the
    confidence of the frames it lifted, whenever it has been idle for a while)."""
    res = Session.open(folder).load_results()
    lifted = sorted(worker.latest)
    res["confidence"][lifted] = 0.0
    return {k: res[k] for k in ("init_mm", "final_mm", "confidence")}


def test_cancel_from_the_page_keeps_the_old_results(ctx: Ctx):
    page, view, folder = ctx.page, ctx.view(), ctx.folder
    journal_path = folder / JOURNAL_FILE
    assert ctx.app.worker.wait_idle(120)  # the lifts of the references shown are done
    before = run_results(folder, ctx.app.worker)
    journal_before = journal_path.read_bytes() if journal_path.exists() else b""
    page.get_by_role("button", name="Propagate & refine").click()
    wait_until(lambda: view.live.filled() >= 8, timeout_s=60, what="a few propagated frames")
    page.get_by_role("button", name="Cancel run").click()
    wait_until(
        lambda: view.runner.status.phase == "cancelled", timeout_s=60, what="the run to stop"
    )
    wait_until(
        lambda: page.get_by_text("cancelled: the session keeps").is_visible(), what="cancel text"
    )
    after = run_results(folder, ctx.app.worker)
    for key in before:
        assert np.array_equal(after[key], before[key], equal_nan=True), (
            f"a cancelled run changed {key} in results.npz"
        )
    journal_after = journal_path.read_bytes() if journal_path.exists() else b""
    assert journal_after == journal_before, "a cancelled run must leave the journal untouched"
    assert not (folder / "propagation_partial.npz").exists()
    assert view.live.filled() == 4  # the view is back to what is on disk


def test_run_streams_frames_before_it_ends(ctx: Ctx):
    page, view = ctx.page, ctx.view()
    runner = view.runner
    assert view.live.filled() == 4
    page.get_by_role("button", name="Propagate & refine").click()
    # While the run is going, the page shows partial progress and skeletons arrive.
    text = wait_until(
        lambda: (m := page.get_by_text("propagating:").all_inner_texts()) and m[0],
        timeout_s=60,
        what="progress text",
    )
    seen_partial = []

    def partial():
        st = runner.status
        filled = view.live.filled()
        label = page.get_by_text("propagating:").all_inner_texts()
        if st.phase == "propagate" and 4 < filled < 40 and label:
            seen_partial.append((filled, label[0]))
        return len(seen_partial) >= 3 and seen_partial[-1][0] > seen_partial[0][0]

    wait_until(partial, timeout_s=60, interval_s=0.2, what="frames filling in during the run")
    assert runner.status.running, "the run should still be going"
    assert "of 36 frames" in text
    wait_until(lambda: runner.status.phase == "done", timeout_s=120, what="the run to finish")
    wait_until(
        lambda: page.get_by_text("done: 36 frame(s) propagated").is_visible(),
        what="done on the page",
    )
    res = Session.open(ctx.folder).load_results()
    assert np.all(np.isfinite(res["final_mm"])) and np.all(
        np.isfinite(res["init_mm"][np.arange(40) % 10 != 0])
    )


def test_worst_frame_fix_becomes_reference_and_only_dependents_change(ctx: Ctx):
    page, view, folder = ctx.page, ctx.view(), ctx.folder
    before = Session.open(folder).load_results()
    assert np.isfinite(before["init_mm"][15]).all(), "needs the previous test's run"
    refs = set(range(0, 40, STEP))
    # The page's click and this probe must walk the same ranking. Until the background ranking
    # of the previous run's final results lands, both get an older one (from mid-run); when it
    # lands between the probe and the click, they walk to different frames (the intermittent
    # failure: more likely on a loaded machine, where ranking and the click's round trip are slow).
    live = view.live
    live.start_ranking()
    wait_until(
        lambda: live.ranked_version() == live.version, what="the ranking of the run's results"
    )
    probe = ReviewState(view.session, view.live, view.runner, "probe")  # the walk, headless
    probe.walked = list(view.state.walked)
    expected = probe.next_worst()
    page.get_by_role("button", name="Next worst frame").click()
    wait_until(lambda: view.frame == expected, what=f"the worst frame {expected}")
    frame = view.frame
    # the shown frame is one marker point on the priority plot (no line that looks like data)
    wait_until(
        lambda: np.flatnonzero(np.isfinite(view.w.plot.data[2])).tolist() == [frame],
        what="the plot's marker on the shown frame",
    )
    assert frame not in refs
    # the page names the frame the shown result was propagated from: the candidate chain
    # propagation kept (results.npz "source"), a temporal neighbour here
    source = int(before["source"][frame])
    assert source in (frame - 1, frame + 1)
    wait_until(
        lambda: page.get_by_text(
            f"Review frame {frame} (refined, propagated from frame {source})"
        ).is_visible(),
        what="the frame text",
    )
    # drag a well separated joint 50 px to the right
    ctx.settle(page, view)
    k, _ = pick_joint(page, view)
    n_before = len(journal(folder))
    drag_gesture(
        page, lambda: pick_joint(page, view, k)[1], (50, 0), settle=lambda: ctx.settle(page, view)
    )
    entry = wait_until(
        lambda: len(journal(folder)) > n_before and journal(folder)[-1], what="the correction"
    )
    cmd = entry["command"]
    assert cmd["kind"] == "batch"
    assert [c["kind"] for c in cmd["commands"]] == ["set_reference", "set_frame", "set_3d"]
    assert cmd["commands"][0] == {
        "frame": frame,
        "kind": "set_reference",
        "is_reference": True,
        "parent": -1,
        "correction": True,
    }
    assert cmd["commands"][2]["joint"] == k
    shown_before = before["final_mm"][frame, k]
    assert cmd["commands"][2]["xyz_mm"][0] - shown_before[0] > 5.0
    reopened = Session.open(folder)
    assert (
        frame in reopened.model.corrections and frame in reopened.model.selection.reference_frames
    )
    reopened.close()
    # the runner lifts the new reference and re-propagates the frames between its neighbouring
    # references only (its descendants, and the frames before it: the backward candidates)
    wait_until(
        lambda: view.runner.history and view.runner.history[-1].kind == "corrections",
        timeout_s=120,
        what="the correction job",
    )
    job = view.runner.history[-1]
    assert job.phase == "done", job.message
    start, end = (frame // STEP) * STEP, (frame // STEP + 1) * STEP
    assert job.frames == [f for f in range(start + 1, end) if f != frame]
    after = Session.open(folder).load_results()
    changed = set(
        np.flatnonzero(
            np.any(~np.isclose(after["init_mm"], before["init_mm"], equal_nan=True), axis=(1, 2))
        )
    )
    # only its dependents change, and they are re-propagated; one whose previous pose explains
    # its depth better keeps it (pipeline._previous_fits_better)
    assert changed <= set(range(start + 1, end)) and changed & set(range(frame + 1, end))
    kept = set(range(frame + 1, end)) - changed
    assert all(np.isfinite(after["model_fit"][f, 0]) for f in kept)  # kept on the fit's evidence
    assert np.allclose(after["lifted_mm"][frame, k], cmd["commands"][2]["xyz_mm"], atol=0.01)
    wait_until(
        lambda: page.get_by_text(f"Review frame {frame} (reference").is_visible(),
        what="reference text",
    )


def pick_joint(page, view, k: int | None = None) -> tuple[int, tuple[float, float]]:
    """The joint farthest (on screen) from every other joint (or joint ``k``), and its page
    position, where the browser draws it."""
    shown = np.asarray(view.hand.joints.batched_scales) > 0
    pts = np.array(
        [screen_of(page, "/hand/joints", p) for p in drawn(page, "/hand/joints")["instances"]]
    )
    pts[~shown] = 1e6
    d = np.linalg.norm(pts[:, None] - pts[None], axis=-1)
    d[np.arange(len(d)), np.arange(len(d))] = np.inf
    k = int(np.argmax(d.min(axis=1))) if k is None else k
    return k, (float(pts[k, 0]), float(pts[k, 1]))


def test_two_pages_edit_the_same_frame_and_nothing_is_lost(ctx: Ctx):
    page_a, folder = ctx.page, ctx.folder
    page_b = open_app(ctx.browser, ctx.app.url)
    try:
        open_review_tab(page_b)
        wait_until(
            lambda: len(ctx.app.review_panels()) == 2,
            what="second view",
        )
        view_a, view_b = ctx.view(0), ctx.view(1)
        frame = 24  # a propagated frame both pages go to via the slider... set from the server side
        for page, view in ((page_a, view_a), (page_b, view_b)):
            view.ui.show("review")
            view.show_frame(frame)
            wait_until(
                lambda p=page: p.get_by_text(f"Review frame {frame} (").is_visible(),
                what="frame text",
            )
        ctx.settle(page_a, view_a)
        k, _ = pick_joint(page_a, view_a)
        n0 = len(journal(folder))
        shown_a = len(notifications_seen(page_a))
        drag_gesture(
            page_a,
            lambda: pick_joint(page_a, view_a, k)[1],
            (40, 0),
            settle=lambda: ctx.settle(page_a, view_a),
        )
        wait_until(lambda: len(journal(folder)) == n0 + 1, what="page A's edit")
        # B's view follows (lift, then re-propagation of the frame's dependents); B then drags the
        # same joint from where B now sees it (settle waits for the re-propagation)
        drag_gesture(
            page_b,
            lambda: pick_joint(page_b, view_b, k)[1],
            (0, 40),
            settle=lambda: ctx.settle(page_b, view_b),
        )
        wait_until(lambda: len(journal(folder)) == n0 + 2, what="page B's edit")
        entries = journal(folder)[n0:]
        assert entries[0]["client"] != entries[1]["client"]
        assert entries[0]["command"]["kind"] == "batch"  # A made the frame a reference
        assert entries[1]["command"]["kind"] == "set_3d"  # B edited the (now) reference: no re-seed
        assert entries[1]["command"]["joint"] == k
        # page A was told about B's edit
        wait_notification(page_a, "Frame edited elsewhere", f"changed frame {frame}", since=shown_a)
        # last write wins for the joint; A's other seeded joints are still there; all after reopening
        ctx.app.session.save()
        reopened = Session.open(folder)
        ann = reopened.annotation(frame)
        assert np.allclose(ann.xyz_mm[k], entries[1]["command"]["xyz_mm"], atol=0.01)
        a_seed = entries[0]["command"]["commands"][1]["annotation"]
        other = (k + 1) % 21
        assert np.allclose(ann.xyz_mm[other], np.asarray(a_seed["xyz_mm"], float)[other], atol=0.01)
        assert frame in reopened.model.corrections
        reopened.close()
        wait_until(lambda: ctx.app.ctx.runner.wait_idle(0.1), timeout_s=120, what="re-propagation")
    finally:
        page_b.close()
        wait_until(
            lambda: len(ctx.app.review_panels()) == 1,
            what="page B gone",
        )


def test_accept_flag_export_and_import(ctx: Ctx, tmp_path):
    page, view, folder = ctx.page, ctx.view(), ctx.folder
    view.show_frame(7)
    page.get_by_role("button", name="Flag").click()
    wait_until(
        lambda: (
            journal(folder)[-1]["command"]
            == {"frame": 7, "kind": "set_review", "status": "flagged"}
        ),
        what="flag entry",
    )
    page.get_by_role("button", name="Accept").click()
    wait_until(lambda: journal(folder)[-1]["command"]["status"] == "accepted", what="accept entry")
    assert Session.open(folder).model.review["7"] == "accepted"
    # export JSON through the browser download
    page.get_by_text("Export / import").click()
    with page.expect_download(timeout=30_000) as info:
        page.get_by_role("button", name="JSON", exact=True).click()
    path = tmp_path / "export.json"
    info.value.save_as(path)
    doc = json.loads(path.read_text())
    assert doc["format"] == "handanno-export" and len(doc["frames"]) == 40
    corrections = ctx.app.session.model.corrections
    assert len(corrections) >= 2 and all(doc["frames"][f]["is_reference"] for f in corrections)
    assert doc["corrections"] == corrections
    # NPZ too (same arrays)
    with page.expect_download(timeout=30_000) as info_npz:
        page.get_by_role("button", name="NPZ", exact=True).click()
    npz_path = tmp_path / "export.npz"
    info_npz.value.save_as(npz_path)
    with np.load(npz_path) as npz:
        assert npz["joints_mm"].shape == (40, 21, 3)
        assert np.allclose(npz["joints_mm"][5], doc["frames"][5]["joints_mm"], atol=1e-3)
    # edit the export (frame 3 moved by 7 mm) and import it back through the upload button
    doc["frames"][3]["joints_mm"] = (np.asarray(doc["frames"][3]["joints_mm"]) + 7.0).tolist()
    path.write_text(json.dumps(doc))
    with page.expect_file_chooser() as chooser:
        page.get_by_role("button", name="Import JSON").click()
    chooser.value.set_files(str(path))
    wait_until(
        lambda: page.get_by_text("imported 40 frames").first.is_visible(),
        timeout_s=30,
        what="import done",
    )
    res = Session.open(folder).load_results()
    assert np.allclose(res["final_mm"][3], np.asarray(doc["frames"][3]["joints_mm"]), atol=1e-3)


def test_annotate_hotkeys_pause_while_the_review_scene_is_shown(ctx: Ctx):
    """viser's hotkeys are page-wide: with the Review scene shown, V or arrow keys must not edit
    or move the hidden annotate frame. Using the Annotate panel brings its scene (and keys) back."""
    page, view, folder = ctx.page, ctx.view(), ctx.folder
    annotate = view.ui.annotate
    view.ui.show("review")
    assert view.scene_active
    joint, entries = annotate.state.joint, len(journal(folder))
    shown = len(notifications_seen(page))
    sync_browser(page, view.client)  # the page has the scene switch before the keys
    page.keyboard.press("ArrowRight")
    page.keyboard.press("v")
    wait_notification(page, "Annotate hotkeys paused", since=shown)
    page.get_by_role("tab", name="Annotate").click()
    page.get_by_role("button", name="Sensor view").click()
    wait_until(lambda: not view.scene_active, what="the annotate scene back")
    sync_browser(page, view.client)
    page.keyboard.press("ArrowRight")
    wait_until(lambda: annotate.state.joint != joint, what="next joint by hotkey")
    annotate.flush()
    # the keys pressed before reached the server before this one, and did nothing
    assert annotate.state.joint == joint + 1 and len(journal(folder)) == entries
    page.get_by_role("tab", name="Review").click()


def test_review_scene_shows_labels_and_the_depth_image(ctx: Ctx):
    """Issue 15: the Review scene can show the joint labels and the depth image (both off by
    default: the cloud and the skeleton are what a reviewer checks)."""
    page, view = ctx.page, ctx.view()
    page.get_by_role("tab", name="Review").click()
    page.get_by_role("button", name="Next worst frame").click()
    wait_until(lambda: view.scene_active, what="the review scene")
    view.ui.flush()
    hand = view.hand
    assert not hand.image.visible and not any(label.visible for label in hand.labels)
    page.get_by_role("checkbox", name="Show labels").check()
    page.get_by_role("checkbox", name="Show depth image").check()
    shown = np.all(np.isfinite(view.live.frame(view.frame)[0]), axis=1)
    wait_until(
        lambda: hand.image.visible and all(hand.labels[k].visible for k in np.flatnonzero(shown)),
        what="labels and depth image on the review scene",
    )
    assert shown.any()
