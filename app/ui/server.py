"""The viser server of handanno: one :class:`~app.control.context.AppContext` per session, one
:class:`~app.ui.client_ui.ClientUI` per browser.

``serve(session_folder)`` opens a session and serves it; ``demo(sessions_dir)`` makes the demo
session once (``handanno_core.pipeline.ensure_demo_session``) and serves it. Both are what the CLI
(app/cli.py) calls; ``python -m app.ui.server SESSION [--host H] [--port P]`` does the same
without the CLI.
"""

from __future__ import annotations

import argparse
import re
import sys
import threading
import time
import traceback
import uuid
from pathlib import Path
from typing import Any

import viser

from handanno_core.session import Session, SessionError, default_writer_command

from ..control.context import AppContext
from ..control.jobs import LiftFunction
from .client_ui import ClientUI
from .guard import harden
from .theme import load_help_markdown


class PortInUseError(OSError):
    """The requested port is taken: the server refuses to move to another one silently."""


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
    """A running annotation server: the viser server, the :class:`AppContext` and a
    :class:`ClientUI` per connected browser. ``review_options`` go to the review runner."""

    def __init__(
        self,
        session: Session,
        host: str = "127.0.0.1",
        port: int = 8080,
        *,
        lift_fn: LiftFunction | None = None,
        review_options: dict[str, Any] | None = None,
        verbose: bool = False,
    ):
        self.server = viser.ViserServer(host=host, port=port, label="handanno", verbose=verbose)
        if port != 0 and self.server.get_port() != port:
            # viser moved to the next free port: two servers on one session, or a surprise URL
            moved = self.server.get_port()
            self.server.stop()
            raise PortInUseError(
                f"port {port} on {host} is already in use (another handanno server?); stop it "
                f"or choose another port with --port (viser would have moved to {moved})"
            )
        self.ctx = AppContext(session, lift_fn=lift_fn, review_options=review_options)
        self.session = session
        self.help_markdown = load_help_markdown()
        self._clients: dict[int, ClientUI] = {}
        self._clients_lock = threading.Lock()
        self.server.gui.configure_theme(
            show_share_button=False, control_layout="floating", control_width="medium",
            dark_mode=False,
        )  # fmt: skip
        self.server.scene.set_up_direction("-y")
        # issue 16: no share tunnel, bounded uploads, per-client rate limit (app/ui/guard.py)
        self.guard = harden(self.server)
        self.server.on_client_connect(self._on_connect)
        self.server.on_client_disconnect(self._on_disconnect)

    # ------------------------------------------------------------------ info
    @property
    def worker(self):
        return self.ctx.worker

    @property
    def frames(self):
        return self.ctx.frames

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

    def clients(self) -> list[ClientUI]:
        """The UI of every connected browser."""
        with self._clients_lock:
            return list(self._clients.values())

    def annotate_panels(self) -> list[Any]:
        return [c.annotate for c in self.clients()]

    def review_panels(self) -> list[Any]:
        return [c.review for c in self.clients()]

    # ------------------------------------------------------------------ clients
    def _on_connect(self, client: viser.ClientHandle) -> None:
        try:
            ui = ClientUI(self.ctx, client, browser_identity(client), self.help_markdown)
        except Exception as exc:  # show it in the page, keep the server up
            traceback.print_exc()
            client.add_notification(
                "The view failed to load", f"{type(exc).__name__}: {exc}", color="red"
            )
            return
        with self._clients_lock:
            self._clients[client.client_id] = ui

    def _on_disconnect(self, client: viser.ClientHandle) -> None:
        with self._clients_lock:
            ui = self._clients.pop(client.client_id, None)
        if ui is not None:
            ui.close()

    # ------------------------------------------------------------------ lifetime
    def stop(self) -> None:
        self.server.stop()
        self.ctx.stop()

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
    review_options: dict[str, Any] | None = None,
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
        app = AnnoServer(
            session, host=host, port=port, lift_fn=lift_fn, review_options=review_options
        )
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
        prog="python -m app.ui.server", description="Serve a handanno session."
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
