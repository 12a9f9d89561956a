"""Helpers for driving the viser app in Chromium with Playwright (sync API).

Every use of viser's private test hooks (``window.__viserMutable``: ``nodeRefFromName``, ``camera``,
``canvas``; see viser-notes.md 4.11) lives here, so a viser upgrade that changes them touches one
file. Screen positions are computed in the page: a point in a node's local frame is taken to
world coordinates by three.js (``localToWorld``) and projected with the browser's own camera, so
the tests do not depend on viser's coordinate conventions.
"""

from __future__ import annotations

import json
import os
import shutil
import socket
import time
from collections.abc import Iterator
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
]
VIEWPORT = {"width": 1280, "height": 720}
ARTIFACTS = Path(__file__).resolve().parents[2] / "test-artifacts"


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
    """A headless Chromium (skips cleanly if playwright or chromium is missing)."""
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        pytest.skip("e2e: playwright is not installed (pip install playwright)")
    exe = chromium_path()
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=exe, headless=True, args=CHROMIUM_ARGS)
        try:
            yield b
        finally:
            b.close()


def open_app(b, url: str, node: str = "/annotate/joints", timeout_s: float = 60.0):
    """New 1280x720 page on ``url``, connected and with ``node`` in the scene."""
    page = b.new_page(viewport=VIEWPORT)
    page.goto(url)
    wait_for_node(page, node, timeout_s)
    dismiss_webgl_toast(page)
    return page


def wait_for_node(page, name: str, timeout_s: float = 60.0) -> None:
    page.wait_for_function(
        "(name) => !document.body.innerText.includes('Connecting...') && window.__viserMutable"
        " && window.__viserMutable.nodeRefFromName[name] !== undefined",
        arg=name,
        timeout=timeout_s * 1000,
    )


def dismiss_webgl_toast(page) -> None:
    """Close viser's "Software WebGL rendering detected" toast (top-left), which eats clicks."""
    try:
        toast = page.get_by_text("Software WebGL rendering detected")
        toast.wait_for(timeout=3000)
        box = toast.locator("xpath=ancestor::div[contains(@class,'mantine-Notification-root')][1]")
        close = box.locator("button")
        if close.count():
            close.first.click()
    except Exception:
        pass  # no toast (hardware GL) or a different layout: tests avoid the top-left corner anyway


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


def camera_state(page) -> list[float]:
    return page.evaluate(
        "() => { const c = window.__viserMutable.camera; return [...c.position.toArray(), ...c.quaternion.toArray(), c.fov]; }"
    )


def wait_camera_still(page, timeout_s: float = 10.0, still_s: float = 0.6) -> None:
    """Wait until the browser camera stops moving (server-set poses animate)."""
    deadline = time.monotonic() + timeout_s
    last = camera_state(page)
    still_since = time.monotonic()
    while time.monotonic() < deadline:
        time.sleep(0.15)
        now = camera_state(page)
        if np.allclose(now, last, atol=1e-6):
            if time.monotonic() - still_since >= still_s:
                return
        else:
            still_since = time.monotonic()
            last = now
    raise AssertionError("browser camera did not settle")


def wait_until(
    predicate, timeout_s: float = 15.0, interval_s: float = 0.1, what: str = "condition"
):
    """Poll ``predicate()`` until it returns a truthy value; return it (or fail naming ``what``)."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s:.0f} s waiting for {what}")
        time.sleep(interval_s)


def drag(page, start: tuple[float, float], end: tuple[float, float], steps: int = 12) -> None:
    page.mouse.move(*start)
    page.mouse.down()
    page.mouse.move(*end, steps=steps)
    page.mouse.up()


def save_screenshot(page, name: str) -> Path:
    ARTIFACTS.mkdir(exist_ok=True)
    path = ARTIFACTS / name
    page.screenshot(path=str(path))
    return path


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
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
