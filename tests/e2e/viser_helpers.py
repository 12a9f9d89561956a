"""Helpers for driving the viser app in Chromium with Playwright (sync API).

Every use of viser's private test hooks lives here, so a viser upgrade that changes them touches
one file: ``window.__viserMutable`` (``nodeRefFromName``, ``camera``, ``canvas``; viser-notes.md
4.11), ``window.__viserSceneTree`` (the props each node has in the browser) and
``window.__viserPointer`` (camera locks and the pointer gesture).

Rule of these tests: wait for an observable state, never for a time. The states used here:

* what the browser *draws*: a node's position and a batched mesh's instance positions, read from
  three.js and compared with the server-side handle (:func:`wait_drawn`);
* that the browser has processed every message the server sent so far (:func:`sync_browser`, a
  hidden label whose text the test bumps and waits for);
* the browser camera standing still over consecutive animation frames (:func:`wait_camera_still`);
* notifications, recorded as they appear (:func:`wait_notification`; they auto-close);
* and, in the tests, journal entries on disk and server-side view state.

Screen positions are computed in the page: a point in a node's local frame is taken to world
coordinates by three.js (``localToWorld``) and projected with the browser's own camera, so the
tests do not depend on viser's coordinate conventions. Gestures (:func:`drag_gesture`,
:func:`click_gesture`) check at the press that the right kind of node took it and retry after
``settle()`` where the scene had moved (a lift landing), instead of failing.
"""

from __future__ import annotations

import json
import os
import shutil
import socket
import time
import uuid
import weakref
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

CHROMIUM_ARGS = [
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--no-first-run",
    # a second page must not throttle the first one's timers and animation frames
    "--disable-background-timer-throttling",
    "--disable-backgrounding-occluded-windows",
    "--disable-renderer-backgrounding",
]
VIEWPORT = {"width": 1280, "height": 720}
#: Where failure screenshots (and traces) go; conftest.py points it into the pytest temp dir.
ARTIFACTS = Path(os.environ.get("HANDANNO_E2E_ARTIFACTS", "/tmp/handanno-e2e-artifacts"))
#: Set by conftest.py (``--e2e-trace``): record a Playwright trace per page, kept on failure.
TRACE = os.environ.get("HANDANNO_E2E_TRACE", "") not in ("", "0")
#: Deadline of every wait: a last resort that only a failing test reaches (waits end on state).
DEADLINE_S = 90.0

_OPEN_PAGES: weakref.WeakSet = weakref.WeakSet()

#: Records every notification as it is added (they auto-close, so polling could miss one).
_NOTIFICATION_RECORDER = """
(() => {
  if (window.__e2eNotifications) return;
  window.__e2eNotifications = [];
  const seen = new WeakSet();
  const record = (el) => {
    if (seen.has(el)) return;
    seen.add(el);
    const title = el.querySelector('.mantine-Notification-title');
    const body = el.querySelector('.mantine-Notification-description');
    window.__e2eNotifications.push({
      title: title ? title.textContent : '',
      message: body ? body.textContent : '',
    });
  };
  new MutationObserver((records) => {
    for (const r of records) for (const n of r.addedNodes) {
      if (n.nodeType !== 1) continue;
      if (n.matches('.mantine-Notification-root')) record(n);
      else for (const el of n.querySelectorAll('.mantine-Notification-root')) record(el);
    }
  }).observe(document, { childList: true, subtree: true });
})();
"""


def chromium_path() -> str:
    """The Chromium binary, or skip the test with a message."""
    path = (
        os.environ.get("HANDANNO_CHROMIUM")
        or shutil.which("chromium")
        or shutil.which("chromium-browser")
    )
    if not path:
        pytest.skip("e2e: no chromium binary on PATH (apt install chromium)")
    return path


@contextmanager
def browser() -> Iterator[object]:
    """A headless Chromium (skips cleanly if playwright or chromium is missing).

    An exception leaving the block saves a screenshot of every open page first (see
    :func:`save_failure_artifacts`), while the pages still exist.
    """
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        pytest.skip("e2e: playwright is not installed (pip install playwright)")
    exe = chromium_path()
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=exe, headless=True, args=CHROMIUM_ARGS)
        try:
            yield b
        except BaseException:
            test = os.environ.get("PYTEST_CURRENT_TEST", "browser").split(" ")[0].split("::")[-1]
            save_failure_artifacts("".join(c if c.isalnum() or c in "-_." else "_" for c in test))
            raise
        finally:
            b.close()


def open_app(b, url: str, node: str = "/hand/joints", timeout_s: float = DEADLINE_S):
    """New 1280x720 page on ``url``, connected and with ``node`` in the scene."""
    page = b.new_page(viewport=VIEWPORT)
    page.add_init_script(_NOTIFICATION_RECORDER)
    page.e2e_console = []  # the browser console, shown with a failure
    page.on("console", lambda msg: page.e2e_console.append(f"{msg.type}: {msg.text}"))
    if TRACE:
        page.context.tracing.start(screenshots=True, snapshots=True)
    _OPEN_PAGES.add(page)
    page.goto(url)
    wait_for_node(page, node, timeout_s)
    dismiss_webgl_toast(page)
    return page


def wait_for_node(page, name: str, timeout_s: float = DEADLINE_S) -> None:
    page.wait_for_function(
        "(name) => !document.body.innerText.includes('Connecting...') && window.__viserMutable"
        " && window.__viserMutable.nodeRefFromName[name] !== undefined",
        arg=name,
        timeout=timeout_s * 1000,
    )


def dismiss_webgl_toast(page) -> None:
    """Close viser's "Software WebGL rendering detected" toast (top-left), which eats clicks.

    viser shows it from a mount effect that runs before the websocket connects, so once a scene
    node exists (open_app) it is there or it never comes (hardware GL).
    """
    toast = page.locator(".mantine-Notification-root").filter(
        has_text="Software WebGL rendering detected"
    )
    if toast.count():
        # a dispatched click: Playwright's actionability checks wait ~10 s on the toast's transition
        toast.first.locator("button").first.dispatch_event("click")
        toast.first.wait_for(state="detached", timeout=DEADLINE_S * 1000)


def close_notifications(page) -> None:
    """Close every notification shown (state: none left in the page)."""
    roots = page.locator(".mantine-Notification-root")
    for button in roots.locator("button").all():
        button.dispatch_event("click")  # see dismiss_webgl_toast
    wait_until(lambda: roots.count() == 0, what="the notifications to close")


def notifications_seen(page) -> list[dict]:
    """Every notification added to the page since it was opened: ``{"title", "message"}``."""
    return page.evaluate("() => window.__e2eNotifications || []")


def wait_notification(
    page, title: str, contains: str = "", since: int = 0, timeout_s: float = DEADLINE_S
) -> list[dict]:
    """Wait until a notification with ``title`` (and ``contains`` in its message) was shown, as
    the ``since``-th notification of the page or later (``len(notifications_seen(page))`` taken
    before the action)."""
    return wait_until(
        lambda: [
            n
            for n in notifications_seen(page)[since:]
            if n["title"] == title and contains in n["message"]
        ],
        timeout_s=timeout_s,
        what=f"a notification {title!r} {contains!r}",
    )


def screen_of(page, node: str, local_xyz) -> tuple[float, float]:
    """Page pixel (x, y) of a point given in ``node``'s local frame."""
    x, y, z = (float(v) for v in np.asarray(local_xyz, dtype=np.float64))
    out = page.evaluate(
        """([name, x, y, z]) => {
            const m = window.__viserMutable;
            const obj = m.nodeRefFromName[name];
            obj.updateMatrixWorld(true);
            m.camera.updateMatrixWorld(true);
            const v = m.camera.position.clone().set(x, y, z);
            obj.localToWorld(v);
            v.project(m.camera);
            const r = m.canvas.getBoundingClientRect();
            return [r.left + (v.x + 1) / 2 * r.width, r.top + (1 - v.y) / 2 * r.height];
        }""",
        [node, x, y, z],
    )
    return float(out[0]), float(out[1])


_DRAWN_JS = """(name) => {
    const m = window.__viserMutable;
    const obj = m && m.nodeRefFromName[name];
    if (!obj) return null;
    obj.updateMatrixWorld(true);
    const out = {position: obj.position.toArray(), instances: null};
    obj.traverse((c) => {
        if (out.instances !== null || !c.isInstancedMesh || !c.getPositionAt) return;
        const inv = obj.matrixWorld.clone().invert();
        out.instances = [];
        for (let i = 0; i < c.instancesCount; i++) {
            const p = c.getPositionAt(i).clone();
            c.localToWorld(p).applyMatrix4(inv);
            out.instances.push(p.toArray());
        }
    });
    return out;
}"""


def drawn(page, node: str) -> dict | None:
    """What the browser draws for ``node``: ``position`` (in its parent's frame) and, for a
    batched mesh, ``instances`` ((N, 3) in the node's frame, as three.js raycasts them)."""
    out = page.evaluate(_DRAWN_JS, node)
    if out is not None and out["instances"] is not None:
        out["instances"] = np.asarray(out["instances"], dtype=np.float64).reshape(-1, 3)
    return out


_POINTS_JS = """(name) => {
    const m = window.__viserMutable;
    const obj = m && m.nodeRefFromName[name];
    if (!obj) return null;
    obj.updateMatrixWorld(true);
    const inv = obj.matrixWorld.clone().invert();
    let out = null;
    obj.traverse((c) => {
        if (out !== null || !c.isPoints || !c.visible) return;
        const a = c.geometry.getAttribute('position');
        out = [];
        const v = m.camera.position.clone();
        for (let i = 0; i < a.count; i++) {
            v.fromBufferAttribute(a, i);
            c.localToWorld(v).applyMatrix4(inv);
            out.push(v.x, v.y, v.z);
        }
    });
    return out;
}"""


def drawn_points(page, node: str) -> np.ndarray | None:
    """The points the browser draws for point cloud ``node``: ``(M, 3)`` in the node's frame, or
    None if the node is missing or hidden."""
    out = page.evaluate(_POINTS_JS, node)
    return None if out is None else np.asarray(out, dtype=np.float64).reshape(-1, 3)


def node_props(page, node: str) -> dict | None:
    """The props the browser holds for ``node`` (e.g. an image's ``render_width``), or None."""
    return page.evaluate(
        """(name) => {
            const t = window.__viserSceneTree;
            const n = t && t.getState()[name];
            if (!n) return null;
            const out = {};
            for (const [k, v] of Object.entries(n.message.props))
                if (typeof v === 'number' || typeof v === 'boolean' || typeof v === 'string')
                    out[k] = v;
            return out;
        }""",
        node,
    )


def screen_of_points(page, node: str, local_xyz) -> tuple[np.ndarray, dict]:
    """Page pixels ``(M, 2)`` of points ``(M, 3)`` in ``node``'s local frame (as
    :func:`screen_of`), and the canvas rectangle ``{left, top, width, height}``."""
    pts = np.asarray(local_xyz, dtype=np.float64).reshape(-1, 3)
    out = page.evaluate(
        """([name, flat]) => {
            const m = window.__viserMutable;
            const obj = m.nodeRefFromName[name];
            obj.updateMatrixWorld(true);
            m.camera.updateMatrixWorld(true);
            const r = m.canvas.getBoundingClientRect();
            const v = m.camera.position.clone();
            const uv = [];
            for (let i = 0; i < flat.length; i += 3) {
                v.set(flat[i], flat[i + 1], flat[i + 2]);
                obj.localToWorld(v);
                v.project(m.camera);
                uv.push(r.left + (v.x + 1) / 2 * r.width, r.top + (1 - v.y) / 2 * r.height);
            }
            return {uv, rect: {left: r.left, top: r.top, width: r.width, height: r.height}};
        }""",
        [node, pts.ravel().tolist()],
    )
    return np.asarray(out["uv"], dtype=np.float64).reshape(-1, 2), out["rect"]


def wait_drawn(page, handle, atol: float = 1e-5, timeout_s: float = DEADLINE_S) -> dict:
    """Wait until the browser draws ``handle`` (a server-side scene handle) where the server has
    put it: its position and, for a batched mesh, every instance position. Returns :func:`drawn`."""

    def same():
        out = drawn(page, handle.name)
        if out is None or not np.allclose(out["position"], handle.position, atol=atol):
            return None
        expected = getattr(handle, "batched_positions", None)
        if expected is not None:
            expected = np.asarray(expected, dtype=np.float64).reshape(-1, 3)
            got = out["instances"]
            if (
                got is None
                or got.shape != expected.shape
                or not np.allclose(got, expected, atol=atol)
            ):
                return None
        return out

    return wait_until(same, timeout_s=timeout_s, what=f"the browser to draw {handle.name}")


_SYNC_HANDLES: dict[int, object] = {}


def sync_browser(page, client, timeout_s: float = DEADLINE_S) -> None:
    """Wait until the browser has processed every message the server queued for ``client`` so
    far: bump the text of a hidden label (``/_e2e/sync``) and wait for the browser to have it
    (messages to one client are applied in order)."""
    token = uuid.uuid4().hex
    handle = _SYNC_HANDLES.get(id(client))
    if handle is None or getattr(handle, "_e2e_client", None) is not client:
        handle = client.scene.add_label("/_e2e/sync", token, visible=False)
        handle._e2e_client = client
        _SYNC_HANDLES[id(client)] = handle
    else:
        handle.text = token
    client.flush()
    page.wait_for_function(
        """(token) => {
            const t = window.__viserSceneTree;
            const node = t && t.getState()['/_e2e/sync'];
            return !!node && node.message.props.text === token;
        }""",
        arg=token,
        timeout=timeout_s * 1000,
    )


def settle_app(page, app, timeout_s: float = DEADLINE_S) -> None:
    """Wait until the app's one browser view holds still: every journaled edit's listeners have
    run (they run under the session lock), the lift worker is idle, and the browser has applied
    everything the server sent it (joints, 2D rings, image, and the camera the server set, which a
    loaded machine can deliver after the page already looks still)."""
    with app.session.lock:
        pass
    assert app.worker.wait_idle(120), "the lift worker did not finish"
    views = app.annotate_panels()
    assert len(views) == 1, f"expected one connected browser, got {len(views)}"
    view = views[0]
    view.flush()
    sync_browser(page, view.client, timeout_s)
    for handle in (view.hand.joints, view.hand.handles2d, view.hand.image):
        wait_drawn(page, handle, timeout_s=timeout_s)
    wait_camera_still(page, timeout_s)


def camera_state(page) -> list[float]:
    return page.evaluate(
        "() => { const c = window.__viserMutable.camera; return [...c.position.toArray(), ...c.quaternion.toArray(), c.fov]; }"
    )


def wait_camera_still(page, timeout_s: float = DEADLINE_S, frames: int = 8) -> None:
    """Wait until the browser camera is the same over ``frames`` consecutive animation frames
    (a server-set pose is applied over a few frames; counting frames, not seconds, keeps this
    right on a loaded machine). Call :func:`sync_browser` first where a camera move may still be
    on its way from the server."""
    page.wait_for_function(
        """(frames) => {
            const c = window.__viserMutable.camera;
            const s = JSON.stringify([...c.position.toArray(), ...c.quaternion.toArray(), c.fov]);
            const w = window.__e2eCamera || (window.__e2eCamera = {s: null, n: 0});
            if (s === w.s) w.n += 1; else { w.s = s; w.n = 0; }
            if (w.n >= frames) { window.__e2eCamera = null; return true; }
            return false;
        }""",
        arg=frames,
        polling="raf",
        timeout=timeout_s * 1000,
    )


def next_frames(page, n: int = 2) -> None:
    """Return after ``n`` animation frames of the page (React commits and effects have run)."""
    page.evaluate(
        """(n) => new Promise((done) => {
            const step = (k) => (k <= 0 ? done() : requestAnimationFrame(() => step(k - 1)));
            step(n);
        })""",
        n,
    )


def wait_until(
    predicate, timeout_s: float = DEADLINE_S, interval_s: float = 0.05, what: str = "condition"
):
    """Poll ``predicate()`` until it returns a truthy value; return it (or fail naming ``what``).

    The deadline is a last resort for a broken build: a passing test returns on the state."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s:.0f} s waiting for {what}")
        time.sleep(interval_s)


# ---------------------------------------------------------------------------------- gestures
def camera_locks(page) -> list[str]:
    """Why viser holds the camera still: non-empty from the press on a draggable node on."""
    return page.evaluate("() => window.__viserPointer.cameraLockReasons()")


def _cancel_press(page) -> None:
    """Give up a press without a click or a drag: a pointercancel for the pressed pointer
    (viser then settles the release as nothing)."""
    page.evaluate(
        """() => {
            const g = window.__viserPointer.getGesture();
            const id = g && g.pointerId !== undefined ? g.pointerId : 1;
            window.dispatchEvent(new PointerEvent('pointercancel', {pointerId: id, bubbles: true}));
        }"""
    )


def _press(page, point, want_draggable: bool) -> bool:
    """Press at ``point``; True if a draggable node took the press iff ``want_draggable``
    (else the press is cancelled and released)."""
    assert not camera_locks(page), f"camera locked before the press: {camera_locks(page)}"
    page.mouse.move(*point)
    page.mouse.down()
    if bool(camera_locks(page)) == want_draggable:
        return True
    _cancel_press(page)
    page.mouse.up()
    return False


def drag_gesture(
    page,
    grab: Callable[[], tuple[float, float]],
    delta: tuple[float, float],
    *,
    settle: Callable[[], None] | None = None,
    attempts: int = 4,
    steps: int = 6,
) -> tuple[float, float]:
    """Drag a scene node by ``delta`` page pixels from the point ``grab()`` returns.

    Before each try ``settle()`` (the caller's wait for a still scene) runs and ``grab()`` is
    recomputed. A press that no draggable node takes (the scene moved in between, e.g. a lift
    landed) is cancelled without a click or a camera orbit and tried again. Returns the start.
    """
    for _ in range(attempts):
        if settle is not None:
            settle()
        start = grab()
        if _press(page, start, want_draggable=True):
            page.mouse.move(start[0] + delta[0], start[1] + delta[1], steps=steps)
            page.mouse.up()
            return start
    raise AssertionError(f"no draggable node under the pointer in {attempts} tries")


def click_gesture(
    page,
    point: Callable[[], tuple[float, float]],
    *,
    settle: Callable[[], None] | None = None,
    attempts: int = 4,
) -> tuple[float, float]:
    """Click at ``point()`` where no draggable node is (e.g. on the depth image, not on a joint
    that a lift has just moved there); retried after ``settle()`` like :func:`drag_gesture`."""
    for _ in range(attempts):
        if settle is not None:
            settle()
        at = point()
        if _press(page, at, want_draggable=False):
            page.mouse.up()
            return at
    raise AssertionError(f"a draggable node was under the click point in {attempts} tries")


def drag(page, start: tuple[float, float], end: tuple[float, float], steps: int = 12) -> None:
    """A plain drag (no checks); prefer :func:`drag_gesture`."""
    page.mouse.move(*start)
    page.mouse.down()
    page.mouse.move(*end, steps=steps)
    page.mouse.up()


# ---------------------------------------------------------------------------------- artifacts
def save_screenshot(page, name: str) -> Path:
    """Screenshot of ``page`` into the failure artifacts folder (the pytest temp dir)."""
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    path = ARTIFACTS / name
    page.screenshot(path=str(path))
    return path


def save_failure_artifacts(label: str) -> list[Path]:
    """Screenshot (and trace, with ``--e2e-trace``) of every open page; console log too."""
    saved = []
    for i, page in enumerate(list(_OPEN_PAGES)):
        try:
            if page.is_closed():
                continue
            stem = f"{label}-page{i}"
            saved.append(save_screenshot(page, f"{stem}.png"))
            (ARTIFACTS / f"{stem}.console.txt").write_text(
                "\n".join(getattr(page, "e2e_console", []))
            )
            if TRACE:
                trace = ARTIFACTS / f"{stem}.trace.zip"
                page.context.tracing.stop(path=str(trace))
                page.context.tracing.start(screenshots=True, snapshots=True)
                saved.append(trace)
        except Exception:  # a crashed page: nothing more to save
            pass
    return saved


def readme_screenshot(page, name: str, tmp_dir: Path) -> Path:
    """Screenshot ``name`` into ``tmp_dir``; with ``HANDANNO_SCREENSHOTS=DIR`` (or
    ``pytest tests/e2e --screenshots DIR``) also into DIR, e.g. static/screenshots for the README.
    A normal test run never writes into the repository."""
    path = Path(tmp_dir) / name
    page.screenshot(path=str(path))
    out = os.environ.get("HANDANNO_SCREENSHOTS")
    if out:
        Path(out).mkdir(parents=True, exist_ok=True)
        shutil.copyfile(path, Path(out) / name)
    return path


# ---------------------------------------------------------------------------------- misc
def free_port() -> int:
    """A free TCP port on the loopback interface."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def journal(folder: Path) -> list[dict]:
    """The session's journal entries as dicts (empty if there is no journal yet)."""
    path = folder / "journal.jsonl"
    if not path.exists():
        return []
    lines = path.read_bytes().split(b"\n")[:-1]  # a line still being written has no newline yet
    return [json.loads(line) for line in lines if line.strip()]
