"""End-to-end: edits made in the page survive a SIGKILL of the server (journal fsynced before "saved")."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import urllib.request
from pathlib import Path

import numpy as np
from viser_helpers import (
    browser,
    camera_state,
    click_gesture,
    drawn,
    free_port,
    journal,
    open_app,
    screen_of,
    wait_camera_still,
    wait_until,
)

from app.control.frames import FrameStore
from app.ui.watchdog import GONE_TITLE
from handanno_core.session import Session

REPO = Path(__file__).resolve().parents[2]


def start_server(folder: Path, port: int, log: Path) -> subprocess.Popen:
    """``python -m app.ui.server`` on ``port``, its output into ``log`` (a pipe nobody reads could
    fill up and block the server); returns once it answers HTTP."""
    with open(log, "ab") as out:
        proc = subprocess.Popen(
            [sys.executable, "-m", "app.ui.server", str(folder), "--port", str(port)],
            cwd=REPO,
            stdout=out,
            stderr=subprocess.STDOUT,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )

    def up() -> bool:
        if proc.poll() is not None:
            raise AssertionError(f"server exited with {proc.returncode}: {log.read_text()}")
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=5) as r:
                return r.status == 200
        except OSError:
            return False

    wait_until(up, interval_s=0.2, what="the server to answer HTTP")
    return proc


def wait_sensor_view(page, geo, camera) -> None:
    """Wait until the page shows frame 0's image where the server puts it, seen from the sensor
    (the server's camera pose has arrived: its field of view is the sensor's) and still."""
    fov_deg = float(np.degrees(2.0 * np.arctan(camera.height / 2.0 / camera.fy)))
    wait_until(
        lambda: (
            (d := drawn(page, "/hand/image")) is not None
            and np.allclose(d["position"], geo.image_position, atol=1e-5)
            and abs(camera_state(page)[7] - fov_deg) < 1e-3
        ),
        what="the sensor view of frame 0",
    )
    wait_camera_still(page)


def test_sigkill_loses_no_acknowledged_edit(session_folder: Path, tmp_path: Path):
    port = free_port()
    log = tmp_path / "server.log"
    before = Session.open(session_folder)
    geo = FrameStore(before).get(0).geometry  # the same geometry the server computes
    camera = before.camera
    uv = np.round(camera.project(geo.centre_mm))
    proc = start_server(session_folder, port, log)
    try:
        with browser() as b:
            page = open_app(b, f"http://127.0.0.1:{port}/")
            click_gesture(  # the wrist, 2D
                page,
                lambda: screen_of(page, "/hand", geo.pixel_to_scene(uv)),
                settle=lambda: wait_sensor_view(page, geo, camera),
            )
            wait_until(lambda: page.get_by_text("(edit #1)").is_visible(), what="saved #1")
            page.keyboard.press("v")  # joint 1 (auto-selected) -> occluded
            wait_until(lambda: page.get_by_text("(edit #2)").is_visible(), what="saved #2")
            page.keyboard.press("d")  # joint 1 depth order -> closer
            wait_until(lambda: page.get_by_text("(edit #3)").is_visible(), what="saved #3")
            os.kill(proc.pid, signal.SIGKILL)  # no chance to snapshot or close anything
            proc.wait(90)
            assert proc.returncode == -signal.SIGKILL
            # the page says so, clearly, instead of looking alive
            banner = page.locator("#handanno-server-gone")
            banner.wait_for(timeout=30_000)
            assert GONE_TITLE in banner.inner_text() and "saved" in banner.inner_text()
            kinds = [e["command"]["kind"] for e in journal(session_folder)]
            assert kinds == ["set_2d", "set_visible", "set_depth_order"]

            proc = start_server(session_folder, port, log)  # the restart replays the journal
            wait_until(lambda: "reload this page" in banner.inner_text(), what="'server back'")
            reopened = Session.open(session_folder)
            ann = reopened.annotation(0)
            assert np.allclose(ann.uv_px[0], uv, atol=1.5)
            assert not ann.visible[1] and ann.depth_order[1] == -1
            page.close()
            page = open_app(b, f"http://127.0.0.1:{port}/")
            # The view opens on the first unplaced joint (1), whose saved state is shown.
            wait_until(
                lambda: page.get_by_text("Visibility: occluded (V)").is_visible(),
                what="joint 1 occluded",
            )
            assert page.get_by_text("Depth vs parent: closer (D)").is_visible()
    finally:
        if proc.poll() is None:
            proc.kill()  # nothing is asserted on the shutdown: do not wait for a graceful one
            proc.wait()
