"""The server without a browser: bad sessions fail clearly, edits re-lift in the worker, demo wiring."""

from __future__ import annotations

import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
from test_app_core import fake_lift, make_session

from app.ui import server as app_server
from app.ui.server import serve
from handanno_core.session import SetJoint2D

REPO = Path(__file__).resolve().parents[1]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run_server_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "app.ui.server", *args],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    )


def test_missing_session_exits_nonzero_with_message(tmp_path):
    r = run_server_cli(str(tmp_path / "nope"), "--port", str(free_port()))
    assert r.returncode == 2
    assert "no such session folder" in r.stderr and "Traceback" not in r.stderr


def test_corrupt_session_exits_nonzero_with_message(tmp_path):
    s = make_session(tmp_path)
    s.close()
    (s.folder / "session.json").write_text('{"version": 1, "name": ')
    r = run_server_cli(str(s.folder), "--port", str(free_port()))
    assert r.returncode == 2
    assert "corrupt session file" in r.stderr and "session.json" in r.stderr


def test_serve_prints_url_and_relifts_edits(tmp_path, capsys):
    s = make_session(tmp_path)
    s.close()
    app = serve(s.folder, port=free_port(), block=False, lift_fn=fake_lift)
    try:
        out = capsys.readouterr().out
        assert f"annotate at http://localhost:{app.port}" in out
        assert app.host == "127.0.0.1"
        entry = app.session.execute(
            SetJoint2D(frame=5, joint=0, uv_px=(150.0, 130.0)), client="test"
        )
        assert app.worker.wait_idle(60)
        outcome = app.worker.latest[5]
        assert outcome.error is None and outcome.journal_seq == entry.seq
        np.testing.assert_allclose(
            outcome.joints_mm[0],
            app.session.camera.backproject(np.array([150.0, 130.0]), np.float64(400.0)),
        )
    finally:
        app.stop()
    assert np.isfinite(app.session.load_results()["lifted_mm"][5]).all()


def test_demo_creates_then_serves(tmp_path, monkeypatch):
    s = make_session(tmp_path)
    s.close()
    calls = []

    def fake_ensure(sessions_dir, frames=300):
        calls.append(Path(sessions_dir))
        return s.folder

    import handanno_core.pipeline as pipeline

    monkeypatch.setattr(pipeline, "ensure_demo_session", fake_ensure)
    app = app_server.demo(tmp_path / "sessions", port=free_port(), block=False)
    try:
        assert calls == [tmp_path / "sessions"]
        assert app.session.folder == s.folder
    finally:
        app.stop()


class FakeStorage:
    """Stand-in for viser's ClientHandle.local_storage (a dict; optionally blocked)."""

    def __init__(self, items=None, blocked=False):
        self.items = dict(items or {})
        self.blocked = blocked

    def get_item(self, key, timeout=None):
        if self.blocked:
            raise RuntimeError("Failed to read localStorage: SecurityError")
        return self.items.get(key)

    def set_item(self, key, value):
        self.items[key] = value


def test_browser_identity_is_kept_in_local_storage():
    """A browser keeps its journal name across reloads (same storage); a blocked or tampered
    storage gets a fresh random name, never another browser's."""
    from types import SimpleNamespace

    first = SimpleNamespace(local_storage=FakeStorage())
    name = app_server.browser_identity(first)
    assert name.startswith("browser-") and len(name) == len("browser-") + 12
    reloaded = SimpleNamespace(local_storage=FakeStorage(first.local_storage.items))
    assert app_server.browser_identity(reloaded) == name
    other = SimpleNamespace(local_storage=FakeStorage())
    assert app_server.browser_identity(other) != name
    blocked = SimpleNamespace(local_storage=FakeStorage(blocked=True))
    a, b = app_server.browser_identity(blocked), app_server.browser_identity(blocked)
    assert a != b and a != name
    tampered = SimpleNamespace(
        local_storage=FakeStorage({app_server.BROWSER_ID_KEY: "../../x; rm -rf"})
    )
    assert app_server.browser_identity(tampered) != "browser-../../x; rm -rf"
