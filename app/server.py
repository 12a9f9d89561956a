"""The viser server of handanno: one session, one lift worker, a set of views per browser.

``serve(session_folder)`` opens a session and serves it; ``demo(sessions_dir)`` makes the demo
session once (``handanno_core.pipeline.ensure_demo_session``) and serves it. Both are what the CLI
(app/cli.py) calls; ``python -m app.server SESSION [--host H] [--port P]`` does the same without
the CLI.

Structure: :class:`AnnoServer` owns the :class:`~handanno_core.session.Session`, a
:class:`~app.frames.FrameStore` and the :class:`~app.worker.LiftWorker`. On every browser
connection it builds a tab group with one tab per entry of :attr:`AnnoServer.view_classes`
(``("Annotate", AnnotateView)`` now; the Review view of issue 8 appends itself there), each a
per-client view object owning that client's scene nodes and panel. The server subscribes to the
session: every acknowledged edit re-lifts its frame in the worker (coalesced) and is forwarded to
the views; lift results are forwarded to the views too.
"""

from __future__ import annotations

import argparse
import html
import json
import re
import sys
import threading
import time
import traceback
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import viser

from handanno_core.session import JournalEntry, Session, SessionError, default_writer_command

from .annotate_state import entry_frame
from .annotate_view import STATIC, AnnotateView
from .frames import FrameStore
from .guard import harden
from .hotkeys import hotkey_table_markdown
from .review_view import ReviewView  # issue 8 (review helper)
from .worker import LiftFunction, LiftOutcome, LiftWorker


def load_help_markdown() -> str:
    try:
        return (STATIC / "help.md").read_text()
    except OSError:
        return "## Hotkeys\n\n" + hotkey_table_markdown()


class PortInUseError(OSError):
    """The requested port is taken: the server refuses to move to another one silently."""


#: viser's own keyboard camera keys (``CAMERA_MOVEMENT_KEYS`` in its client, 1.1.x), by
#: ``KeyboardEvent.code``. viser 1.1 has no setting to turn them off (viser issue #366), and the
#: app's hotkeys D and arrows would move the camera and break the image alignment.
CAMERA_KEYS = ("KeyW", "KeyA", "KeyS", "KeyD", "KeyQ", "KeyE") + tuple(
    f"Arrow{d}" for d in ("Up", "Down", "Left", "Right")
)
#: Added to every page as a GUI HTML element (viser runs no <script>, an inline error handler
#: runs once). Key events of CAMERA_KEYS stop at <html>: the command palette's hotkeys listen
#: there and still fire, viser's camera listener on ``document`` never sees them. Enter or Escape
#: in a text or number box leaves the box, so the hotkeys (ignored while a box has focus) work
#: again. tests/e2e/test_usability.py presses D and the arrows and checks the camera.
_KEYBOARD_JS = """
if (!window.__handannoKeys) {
  window.__handannoKeys = true;
  const cam = new Set(CAMERA_KEYS_JSON);
  const stop = (e) => { if (cam.has(e.code)) e.stopPropagation(); };
  document.documentElement.addEventListener("keydown", stop);
  document.documentElement.addEventListener("keyup", stop);
  document.addEventListener("keydown", (e) => {
    const t = e.target;
    if ((e.key === "Enter" || e.key === "Escape") && t && t.tagName === "INPUT") t.blur();
  }, true);
}
""".replace("CAMERA_KEYS_JSON", json.dumps(CAMERA_KEYS))
KEYBOARD_SHIM = (
    '<img alt="" src="data:," style="display:none" onerror="'
    + html.escape(" ".join(_KEYBOARD_JS.split()))
    + '">'
)


#: localStorage key of this app's per-browser id (viser namespaces it under its own prefix).
BROWSER_ID_KEY = "handanno.browser_id"
_BROWSER_ID = re.compile(r"[0-9a-f]{12}")


def browser_identity(client: Any, timeout_s: float = 3.0) -> str:
    """``browser-<id>``: the name this browser's edits carry in the journal.

    The id is random and kept in the browser's localStorage, so a page reload (or a restarted
    server) gives the same name, and with it the same undo history, which the session rebuilds per
    name from the journal. Where storage is blocked or does not answer, a fresh random id: such a
    browser never takes over another's history (viser's client ids restart at 0 with the server).
    """
    stored = None
    try:
        stored = client.local_storage.get_item(BROWSER_ID_KEY, timeout=timeout_s)
    except (RuntimeError, TimeoutError, AttributeError):
        pass
    if stored is not None and _BROWSER_ID.fullmatch(stored):
        return f"browser-{stored}"
    new_id = uuid.uuid4().hex[:12]
    try:
        client.local_storage.set_item(BROWSER_ID_KEY, new_id)
    except (RuntimeError, AttributeError):
        pass
    return f"browser-{new_id}"


class AnnoServer:
    """A running annotation server; see the module docstring."""

    #: (tab label, view class). A view class takes ``(app, client)`` and may define
    #: ``on_entry(entry, frame)``, ``on_lift(outcome)`` and ``close()``.
    view_classes: list[tuple[str, type]] = [("Annotate", AnnotateView)]
    # --- issue 8 (review helper): the Review tab ---
    view_classes = [*view_classes, ("Review", ReviewView)]
    # --- end issue 8 ---

    def __init__(
        self,
        session: Session,
        host: str = "127.0.0.1",
        port: int = 8080,
        *,
        lift_fn: LiftFunction | None = None,
        verbose: bool = False,
    ):
        self.session = session
        self.frames = FrameStore(session)
        self.help_markdown = load_help_markdown()
        self.worker = LiftWorker(
            session,
            self.frames,
            lift_fn=lift_fn,
            on_result=self._on_lift,
            initial_guess=self.prefill,
        )
        self.views: dict[int, dict[str, Any]] = {}
        self.client_names: dict[int, str] = {}  # viser client id -> journal name (see above)
        self._views_lock = threading.Lock()
        #: callbacks(view, outcome) after a view assigned a lifted skeleton (benchmarks).
        self.skeleton_listeners: list[Callable[[Any, LiftOutcome], None]] = []
        self.server = viser.ViserServer(host=host, port=port, label="handanno", verbose=verbose)
        if port != 0 and self.server.get_port() != port:
            # viser moved to the next free port: two servers on one session, or a surprise URL
            moved = self.server.get_port()
            self.server.stop()
            raise PortInUseError(
                f"port {port} on {host} is already in use (another handanno server?); stop it "
                f"or choose another port with --port (viser would have moved to {moved})"
            )
        self.server.gui.configure_theme(
            show_share_button=False,
            control_layout="floating",
            control_width="medium",
            dark_mode=False,
        )
        self.server.scene.set_up_direction("-y")
        # issue 16: no share tunnel, bounded uploads, per-client rate limit (app/guard.py)
        self.guard = harden(self.server)
        self.worker.start()
        self._unsubscribe = session.subscribe(self._on_entry)
        self.server.on_client_connect(self._on_connect)
        self.server.on_client_disconnect(self._on_disconnect)

    # ------------------------------------------------------------------ info
    @property
    def host(self) -> str:
        return self.server.get_host()

    @property
    def port(self) -> int:
        return self.server.get_port()

    @property
    def url(self) -> str:
        host = self.host
        return f"http://{'localhost' if host in ('127.0.0.1', '0.0.0.0') else host}:{self.port}"

    def prefill(self, frame: int) -> np.ndarray | None:
        """``(J, 3)`` mm pre-filled joints of ``frame`` (:func:`handanno_core.prefill.prefill_reference`:
        the frame's own results, else one propagation step from the nearest frame with joints),
        or None. Never raises: a failed pre-fill only means no first guess."""
        from handanno_core.prefill import prefill_reference

        try:
            joints = prefill_reference(self.session, frame, None)
        except Exception:
            traceback.print_exc()
            return None
        if joints is None or not np.all(np.isfinite(joints)):
            return None
        return np.asarray(joints, dtype=np.float64)

    def annotate_views(self) -> list[AnnotateView]:
        with self._views_lock:
            return [v["Annotate"] for v in self.views.values() if "Annotate" in v]

    # ------------------------------------------------------------------ clients
    def client_name(self, client: viser.ClientHandle) -> str:
        """The journal name of ``client``'s edits (stable across reloads of that browser)."""
        name = self.client_names.get(client.client_id)
        if name is None:
            name = self.client_names[client.client_id] = browser_identity(client)
        return name

    def _on_connect(self, client: viser.ClientHandle) -> None:
        views: dict[str, Any] = {}
        self.client_name(client)  # before the views: they journal under it
        client.gui.add_html(KEYBOARD_SHIM)
        try:
            if len(self.view_classes) > 1:
                tabs = client.gui.add_tab_group()
                for label, cls in self.view_classes:
                    with tabs.add_tab(label):
                        views[label] = cls(self, client)
            else:
                label, cls = self.view_classes[0]
                views[label] = cls(self, client)
        except Exception as exc:  # show it in the page, keep the server up
            traceback.print_exc()
            client.add_notification(
                "The view failed to load", f"{type(exc).__name__}: {exc}", color="red"
            )
        with self._views_lock:
            self.views[client.client_id] = views

    def _on_disconnect(self, client: viser.ClientHandle) -> None:
        with self._views_lock:
            views = self.views.pop(client.client_id, {})
        self.client_names.pop(client.client_id, None)
        for view in views.values():
            close = getattr(view, "close", None)
            if close is not None:
                close()

    def _all_views(self) -> list[Any]:
        with self._views_lock:
            return [v for views in self.views.values() for v in views.values()]

    # ------------------------------------------------------------------ session and worker events
    def _on_entry(self, entry: JournalEntry) -> None:
        """Every acknowledged edit (called by the session, under its lock): re-lift, tell the views."""
        frame = entry_frame(entry)
        if frame >= 0:
            self.worker.submit(frame)
        for view in self._all_views():
            handler = getattr(view, "on_entry", None)
            if handler is not None:
                try:
                    handler(entry, frame)
                except Exception:
                    traceback.print_exc()

    def _on_lift(self, frame: int, outcome: LiftOutcome) -> None:
        for view in self._all_views():
            handler = getattr(view, "on_lift", None)
            if handler is not None:
                try:
                    handler(outcome)
                except Exception:
                    traceback.print_exc()

    def notify_skeleton_update(self, view: Any, outcome: LiftOutcome) -> None:
        for listener in list(self.skeleton_listeners):
            listener(view, outcome)

    # ------------------------------------------------------------------ lifetime
    def stop(self) -> None:
        self._unsubscribe()
        # --- issue 8 (review helper): stop the review runner before the session closes ---
        hub = getattr(self, "review_hub", None)
        if hub is not None:
            hub.stop()
        # --- end issue 8 ---
        self.worker.stop()
        self.server.stop()
        self.session.close()

    def wait(self) -> None:
        """Block until Ctrl+C, then stop cleanly."""
        try:
            while True:
                time.sleep(1.0)
        except KeyboardInterrupt:
            print("\nstopping (every edit is already saved)")
        finally:
            self.stop()


def serve(
    session_folder: Path,
    host: str = "127.0.0.1",
    port: int = 8080,
    block: bool = True,
    *,
    lift_fn: LiftFunction | None = None,
) -> AnnoServer:
    """Open the session at ``session_folder`` and serve the annotation app (prints the URL).

    Raises :class:`SessionError` (with a message naming the file) for a missing or corrupt session.
    With ``block=True`` runs until Ctrl+C.
    """
    # One writer per session (issue 16): refuse to start while another process writes it; the
    # message names that process's PID and command.
    session = Session.open(Path(session_folder), writer=default_writer_command())
    try:
        session.open_sequence()
    except SessionError as exc:
        print(f"warning: {exc}\n(the app will show frames as missing)", file=sys.stderr)
    try:
        app = AnnoServer(session, host=host, port=port, lift_fn=lift_fn)
    except PortInUseError:
        session.close()
        raise
    done, total = session.progress()
    print(f"handanno: session {session.model.name}: {total} reference frames, {done} annotated")
    print(
        f"handanno: annotate at {app.url}  (Ctrl+C to stop; every edit is saved as you make it)",
        flush=True,
    )
    if not app.worker.available:
        print(
            "handanno: warning: live lifting unavailable (handanno_core.lift missing)",
            file=sys.stderr,
        )
    if block:
        app.wait()
    return app


def demo(
    sessions_dir: Path = Path("sessions"),
    host: str = "127.0.0.1",
    port: int = 8080,
    block: bool = True,
    frames: int = 300,
) -> AnnoServer:
    """Create ``sessions_dir/demo`` from a ``frames``-frame synthetic sequence once, then serve it."""
    from handanno_core.pipeline import ensure_demo_session

    folder = ensure_demo_session(sessions_dir, frames=frames)
    return serve(folder, host=host, port=port, block=block)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m app.server", description="Serve a handanno session."
    )
    parser.add_argument("session", type=Path, help="session folder")
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, default=8080)
    args = parser.parse_args(argv)
    try:
        serve(args.session, host=args.host, port=args.port, block=True)
    except (SessionError, PortInUseError) as exc:
        print(f"handanno: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
