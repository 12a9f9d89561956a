"""Our own small layer over viser's experimental command palette (``gui.add_command``).

Every hotkey of the app is declared once in :data:`HOTKEYS` (which also feeds the help text),
and bound with :func:`bind`. If a viser release drops or changes ``add_command``, only this module
changes; the buttons in the panel keep working either way.
"""

from __future__ import annotations

import html
import json
import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Hotkey:
    action: str  # our action id, e.g. "undo"
    label: str  # shown in the command palette and the help table
    key: str  # viser HotkeyKey: "A".."Z", "0".."9", "arrowleft", ...
    modifier: str | None = None  # None, "cmd/ctrl", "shift", "cmd/ctrl+shift", ...
    description: str = ""

    @property
    def keys_text(self) -> str:
        names = {"arrowleft": "←", "arrowright": "→", "arrowup": "↑", "arrowdown": "↓"}
        key = names.get(self.key, self.key.upper() if len(self.key) == 1 else self.key)
        mod = {
            None: "",
            "cmd/ctrl": "Ctrl/⌘ + ",
            "cmd/ctrl+shift": "Ctrl/⌘ + Shift + ",
            "shift": "Shift + ",
        }
        return mod.get(self.modifier, f"{self.modifier} + ") + key


#: viser's keyboard camera keys, which the app turns off (KEYBOARD_SHIM below): the
#: hotkeys D and the arrows would otherwise also move the camera and break the image alignment.
CAMERA_KEYS_TEXT = "W A S D Q E, ← → ↑ ↓"
CAMERA_KEYS_NOTE = (
    "viser's keyboard camera is off: these keys never move the camera (orbit, pan and zoom "
    "with the mouse; *Sensor view* resets it)"
)

HOTKEYS: tuple[Hotkey, ...] = (
    Hotkey(
        "next_frame",
        "Next reference frame",
        "N",
        description="go to the next reference frame (Review scene: the next frame)",
    ),
    Hotkey(
        "prev_frame",
        "Previous reference frame",
        "P",
        description="go to the previous reference frame (Review scene: the previous frame)",
    ),
    Hotkey("next_joint", "Next joint", "arrowright", description="select the next joint"),
    Hotkey("prev_joint", "Previous joint", "arrowleft", description="select the previous joint"),
    Hotkey(
        "toggle_visibility",
        "Toggle visibility",
        "V",
        description="selected joint: visible ⇄ occluded",
    ),
    Hotkey(
        "cycle_depth_order",
        "Cycle depth order",
        "D",
        description="selected joint vs its parent: unknown → closer → farther",
    ),
    Hotkey(
        "clear_joint",
        "Clear joint",
        "X",
        description="remove the selected joint's placement (or its outside-the-image mark)",
    ),
    Hotkey(
        "toggle_outside",
        "Outside the image",
        "O",
        description="selected joint lies past the image's border, where nobody can click it "
        "(again: take the mark away)",
    ),
    Hotkey(
        "accept_guesses",
        "Accept guesses",
        "G",
        description="place every joint not placed yet where its guess is drawn (one undo step)",
    ),
    Hotkey(
        "toggle_click_mode",
        "Toggle click mode",
        "M",
        description="clicks place 2D on the image ⇄ 3D on the cloud",
    ),
    Hotkey("undo", "Undo", "Z", "cmd/ctrl", "undo your last edit"),
    Hotkey("redo", "Redo", "Z", "cmd/ctrl+shift", "redo your last undone edit"),
)


#: hotkeys of the Review tab; they act while the Review scene is shown (N / P above move its frame)
REVIEW_HOTKEYS: tuple[Hotkey, ...] = (
    Hotkey(
        "review_accept",
        "Review: accept frame",
        "A",
        description="mark the shown frame accepted and go to the next worst frame",
    ),
    Hotkey("review_flag", "Review: flag frame", "F", description="mark the shown frame flagged"),
    Hotkey(
        "review_next_worst",
        "Review: next worst frame",
        "W",
        description="go to the frame with the next lowest review score",
    ),
)


def bind(gui: Any, hotkey: Hotkey, callback: Callable[[Any], None]) -> Any | None:
    """Register ``hotkey`` on ``gui`` (a viser GuiApi, e.g. ``client.gui``); ``callback(client)``
    runs on trigger. Returns the command handle, or None where the API is unavailable."""
    add_command = getattr(gui, "add_command", None)
    if add_command is None:
        log.warning("viser has no add_command: hotkey %s not bound", hotkey.keys_text)
        return None
    try:
        handle = add_command(
            hotkey.label,
            description=hotkey.description or None,
            hotkey=hotkey.key,
            modifier=hotkey.modifier,
        )
    except (TypeError, ValueError) as exc:
        log.warning("cannot bind hotkey %s: %s", hotkey.keys_text, exc)
        return None

    @handle.on_trigger
    def _(event: Any) -> None:
        callback(getattr(event, "client", None))

    return handle


def bind_all(
    gui: Any, actions: dict[str, Callable[[Any], None]], hotkeys: tuple[Hotkey, ...] = HOTKEYS
) -> dict[str, Any]:
    """Bind every entry of ``hotkeys`` (default :data:`HOTKEYS`) whose action is in ``actions``."""
    return {hk.action: bind(gui, hk, actions[hk.action]) for hk in hotkeys if hk.action in actions}


def hotkey_table_markdown() -> str:
    """The hotkey table of static/help.md (a test keeps the two in sync)."""
    rows = ["| Keys | Action | What it does |", "|---|---|---|"]
    rows += [f"| {hk.keys_text} | {hk.label} | {hk.description} |" for hk in HOTKEYS]
    rows += [f"| {hk.keys_text} | {hk.label} | {hk.description} |" for hk in REVIEW_HOTKEYS]
    rows.append(f"| {CAMERA_KEYS_TEXT} | Camera | {CAMERA_KEYS_NOTE} |")
    return "\n".join(rows)


#: viser's own keyboard camera keys (``CAMERA_MOVEMENT_KEYS`` in its client, 1.1.x), by
#: ``KeyboardEvent.code``. viser 1.1 has no setting to turn them off (viser issue #366), and the
#: app's hotkeys D and arrows would move the camera and break the image alignment.
CAMERA_KEYS = ("KeyW", "KeyA", "KeyS", "KeyD", "KeyQ", "KeyE") + tuple(
    f"Arrow{d}" for d in ("Up", "Down", "Left", "Right")
)
#: Added to every page as a GUI HTML element (viser runs no <script>, an inline error handler
#: runs once). Key events of CAMERA_KEYS stop at <html>: the command palette's hotkeys listen
#: there and still fire, viser's camera listener on ``document`` never sees them. Enter or Escape
#: in a text or number box, or a press on the 3D scene, leaves the box, so the hotkeys (ignored while a box has focus) work
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
  document.addEventListener("pointerdown", (e) => {
    const a = document.activeElement;
    if (e.target && e.target.tagName === "CANVAS" && a && a.tagName === "INPUT") a.blur();
  }, true);
}
""".replace("CAMERA_KEYS_JSON", json.dumps(CAMERA_KEYS))
KEYBOARD_SHIM = (
    '<img alt="" src="data:," style="display:none" onerror="'
    + html.escape(" ".join(_KEYBOARD_JS.split()))
    + '">'
)
