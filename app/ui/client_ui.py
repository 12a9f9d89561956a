"""One browser's UI: the shared :class:`~app.ui.hand_scene.HandScene`, the Annotate and Review
panels (one tab each), the hotkeys, and the observable :class:`ClientState` that says which
panel's scene is shown.

Which scene is shown is one value, ``ClientState.active_scene``; using a panel sets it and the
scene is redrawn by that panel (nothing is toggled node by node, no panel calls the other). All
redraws run on this client's ONE serial UI thread (:meth:`ClientUI.post`), in order: edits, lift
results, job progress and navigation from different threads never interleave half-drawn states,
and the event bus's publishers (the session listener holds the session lock) only enqueue.
"""

from __future__ import annotations

import traceback
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any, Literal

import viser

from ..control.context import AppContext
from ..control.events import Update
from .annotate_panel import AnnotatePanel
from .hand_scene import HandScene
from .hotkeys import HOTKEYS, KEYBOARD_SHIM, REVIEW_HOTKEYS, bind_all
from .review_panel import ReviewPanel
from .watchdog import SERVER_WATCH_SHIM

Scene = Literal["annotate", "review"]


@dataclass
class ClientState:
    """Observable per-browser UI state: ``connect(fn)``; ``fn(state)`` runs after every change."""

    active_scene: Scene = "annotate"
    _listeners: list[Callable[[ClientState], None]] = field(default_factory=list, repr=False)

    def connect(self, fn: Callable[[ClientState], None]) -> None:
        self._listeners.append(fn)

    def set_scene(self, scene: Scene) -> bool:
        """Show ``scene``; False if it was already shown."""
        if scene == self.active_scene:
            return False
        self.active_scene = scene
        for fn in list(self._listeners):
            fn(self)
        return True


class ClientUI:
    """See the module docstring. ``name``: the journal name of this browser's edits."""

    def __init__(self, ctx: AppContext, client: viser.ClientHandle, name: str, help_md: str):
        self.ctx = ctx
        self.client = client
        self.name = name
        self.state = ClientState()
        self._ui = ThreadPoolExecutor(1, thread_name_prefix=f"client-{client.client_id}")
        self._told: set[bool] = set()  # notifications shown once
        client.gui.add_html(KEYBOARD_SHIM)
        client.gui.add_html(SERVER_WATCH_SHIM)
        self.scene = HandScene(client, ctx.session)
        tabs = client.gui.add_tab_group()
        with tabs.add_tab("Annotate"):
            self.annotate = AnnotatePanel(self, help_md)
        with tabs.add_tab("Review"):
            self.review = ReviewPanel(self)
        self.scene.panel = self.annotate.clicks
        self.state.connect(self._on_state)
        self._bind_hotkeys()
        self._unsubscribe = ctx.bus.subscribe(self._on_update)
        self.annotate.activate(reset_camera=True)

    # ------------------------------------------------------------------ the UI thread
    def post(self, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> None:
        """Run ``fn`` on this client's UI thread (after everything posted before)."""

        def run() -> None:
            try:
                fn(*args, **kwargs)
            except Exception:
                traceback.print_exc()

        try:
            self._ui.submit(run)
        except RuntimeError:  # shut down: the client is gone
            pass

    def flush(self, timeout: float = 30.0) -> None:
        """Wait until every posted redraw has run (tests and benchmarks)."""
        self._ui.submit(lambda: None).result(timeout)

    def _on_update(self, update: Update) -> None:
        self.post(self.annotate.on_update, update)
        self.post(self.review.on_update, update)

    # ------------------------------------------------------------------ scenes
    def show(self, scene: Scene) -> None:
        """Show ``scene`` (called when a panel is used); its panel redraws the shared scene."""
        self.state.set_scene(scene)

    def _on_state(self, state: ClientState) -> None:
        panel = self.review if state.active_scene == "review" else self.annotate
        self.scene.panel = self.review if panel is self.review else self.annotate.clicks
        self.post(panel.activate, reset_camera=True)
        other = self.annotate if panel is self.review else self.review
        self.post(other.deactivated)

    # ------------------------------------------------------------------ hotkeys
    def _bind_hotkeys(self) -> None:
        """Hotkeys are page-wide in viser: each acts on the panel whose scene is shown. The frame
        keys N / P move the Review scene's frame there; other Annotate keys do nothing on the
        Review scene (and say so once), and the Review keys act on the Review scene only."""
        a, r = self.annotate, self.review
        annotate = {
            "next_frame": (a.next_frame, lambda: r.step_frame(+1)),
            "prev_frame": (a.prev_frame, lambda: r.step_frame(-1)),
            "next_joint": (lambda: a.select_joint(a.state.joint + 1), None),
            "prev_joint": (lambda: a.select_joint(a.state.joint - 1), None),
            "toggle_visibility": (a.toggle_visibility, None),
            "cycle_depth_order": (a.cycle_depth_order, None),
            "clear_joint": (a.clear_joint, None),
            "toggle_outside": (a.toggle_outside, None),
            "accept_guesses": (a.accept_guesses, None),
            "toggle_click_mode": (a.toggle_click_mode, None),
            "undo": (a.undo, None),
            "redo": (a.redo, None),
        }
        review = {
            "review_accept": (None, r.accept),
            "review_flag": (None, r.flag),
            "review_next_worst": (None, r.go_worst),
        }
        gui = self.client.gui
        bind_all(gui, {k: self._hotkey(*v) for k, v in annotate.items()}, HOTKEYS)
        bind_all(gui, {k: self._hotkey(*v) for k, v in review.items()}, REVIEW_HOTKEYS)

    def _hotkey(self, on_annotate: Callable[[], Any] | None, on_review: Callable[[], Any] | None):
        def run(_client: Any) -> None:
            action = on_review if self.state.active_scene == "review" else on_annotate
            if action is not None:
                action()
            elif (on_annotate is None) not in self._told:
                self._told.add(on_annotate is None)
                if on_annotate is None:
                    title, body = (
                        "Review hotkeys",
                        (
                            "A / F / W act while the Review scene is shown (use the Review panel first)."
                        ),
                    )
                else:
                    title, body = (
                        "Annotate hotkeys paused",
                        (
                            "The Review scene is shown. Use the Annotate panel, or 'Show annotate "
                            "scene' in the Review tab, to annotate again."
                        ),
                    )
                self.client.add_notification(title, body, auto_close_seconds=6.0)

        return run

    def close(self) -> None:
        """The browser disconnected: nothing to persist (edits are journaled as they happen)."""
        self._unsubscribe()
        self.review.close()
        self._ui.shutdown(wait=False, cancel_futures=True)
