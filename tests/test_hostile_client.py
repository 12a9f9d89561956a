"""Hostile browsers (issue 16), spoken to over a raw websocket in viser's wire format.

* a ``ShareUrlRequest`` is refused: no tunnel object, no child process;
* a flood of 3000 clicks from one client leaves another client's panel built, and its own click
  answered, within 2 s (the per-client rate limit of app/ui/guard.py coalesces the flood);
* an upload declaring more than the cap is refused before a byte is buffered (the browser is told
  why), and a half-sent upload is freed when its client disconnects.
"""

from __future__ import annotations

import asyncio
import json
import multiprocessing
import time

import msgspec
import pytest
import viser
import websockets
import zstandard
from test_app_core import fake_lift, make_session
from test_app_server import free_port
from viser import _messages

from app.ui.guard import MAX_UPLOAD_BYTES
from app.ui.server import serve
from handanno_core.export import import_json
from handanno_core.session import SessionError


def encode(message: _messages.Message) -> bytes:
    return msgspec.msgpack.encode(message.as_serializable_dict())


def decode(frame: bytes) -> list[dict]:
    """Server -> client frame: sizes, zstd msgpack ``{"messages": [...]}``, binary buffers."""
    inner, compressed = int.from_bytes(frame[:8], "little"), int.from_bytes(frame[8:16], "little")
    raw = zstandard.ZstdDecompressor().decompress(frame[16 : 16 + compressed], inner)
    return msgspec.msgpack.decode(raw)["messages"]


class RawClient:
    """A browser reduced to a websocket: collects every message the server sends it."""

    def __init__(self, port: int):
        self.port = port
        self.messages: list[tuple[float, dict]] = []

    async def __aenter__(self) -> RawClient:
        self.ws = await websockets.connect(
            f"ws://127.0.0.1:{self.port}",
            subprotocols=[f"viser-v{viser.__version__}"],
            max_size=None,
        )
        self._reader = asyncio.create_task(self._read())
        # viser counts a client as connected (and builds its panel) on its first camera message
        await self.send(
            _messages.ViewerCameraMessage(
                (1.0, 0.0, 0.0, 0.0),
                (0.0, 0.0, -1.0),
                1.0,
                0.01,
                100.0,
                480,
                640,
                (0, 0, 0),
                (0, -1, 0),
            )
        )
        return self

    async def __aexit__(self, *exc: object) -> None:
        self._reader.cancel()
        await self.ws.close()

    async def _read(self) -> None:
        async for frame in self.ws:
            now = time.monotonic()
            for m in decode(frame):
                self.messages.append((now, m))
                if m["type"] == "LocalStorageGetItemRequestMessage":  # a fresh browser: no id yet
                    await self.send(
                        _messages.LocalStorageGetItemResponseMessage(None, None, m["request_uuid"])
                    )

    async def send(self, message: _messages.Message) -> None:
        await self.ws.send(encode(message))

    def find(self, type_name: str, label_prefix: str = "") -> dict | None:
        for _, m in self.messages:
            if m["type"] == type_name and str(m.get("props", {}).get("label", "")).startswith(
                label_prefix
            ):
                return m
        return None

    async def wait_for(self, predicate, timeout: float) -> float:
        """Seconds until some received message satisfies ``predicate`` (raises on timeout)."""
        deadline = time.monotonic() + timeout
        start = time.monotonic()
        seen = 0
        while time.monotonic() < deadline:
            for t, m in self.messages[seen:]:
                if predicate(m):
                    return t - start
            seen = len(self.messages)
            await asyncio.sleep(0.01)
        raise TimeoutError("no such message")


def _markdown(m: dict) -> str:
    """The markdown a GUI update message sets ('' for any other message)."""
    return str(m["updates"].get("_markdown", "")) if m["type"] == "GuiUpdateMessage" else ""


def is_button(label: str):
    return lambda m: m["type"] == "GuiButtonMessage" and m["props"]["label"].startswith(label)


@pytest.fixture
def app(tmp_path):
    s = make_session(tmp_path)
    s.close()
    app = serve(s.folder, port=free_port(), block=False, lift_fn=fake_lift)
    yield app
    app.stop()


def test_share_url_request_is_refused_and_no_tunnel_starts(app):
    async def run() -> None:
        async with RawClient(app.port) as c:
            await c.wait_for(is_button("Visibility"), 20)
            await c.send(_messages.ShareUrlRequest())
            await asyncio.sleep(1.0)
            assert not any(m["type"] == "ShareUrlUpdated" and m["share_url"] for _, m in c.messages)

    asyncio.run(run())
    assert app.guard["share_refused"]  # the request arrived and was refused
    assert app.server._share_tunnel is None and not multiprocessing.active_children()
    with pytest.raises(RuntimeError, match="never opens a share tunnel"):
        app.server.request_share_url()


def test_flood_from_one_client_leaves_another_responsive(app):
    timings: dict[str, float] = {}

    async def run() -> None:
        async with RawClient(app.port) as a:
            await a.wait_for(is_button("Visibility"), 20)
            button = a.find("GuiButtonMessage", "Visibility")["uuid"]
            flood = [_messages.GuiUpdateMessage(button, {"value": True}) for _ in range(3000)]
            for message in flood:  # as fast as the socket takes them
                await a.send(message)
            async with RawClient(app.port) as b:
                timings["panel_s"] = await b.wait_for(is_button("Visibility"), 10)
                # click once the panel shows its first frame, as a person would (a click sent
                # before the panel's callbacks are bound would be lost)
                await b.wait_for(lambda m: "**Frame 0**" in _markdown(m), 10)
                nav = b.find("GuiButtonGroupMessage", "Frame")
                await b.send(_messages.GuiUpdateMessage(nav["uuid"], {"value": "Next (N) ▶"}))
                timings["click_s"] = await b.wait_for(
                    lambda m: "**Frame " in _markdown(m) and "**Frame 0**" not in _markdown(m), 10
                )
            timings["a_dropped"], timings["a_coalesced"] = app.guard["limiter"].stats(0)

    asyncio.run(run())
    print(
        f"flood of 3000 clicks: other client's panel in {timings['panel_s']:.2f} s, its click "
        f"answered in {timings['click_s']:.2f} s; flood coalesced {timings['a_coalesced']}"
    )
    assert timings["panel_s"] < 2.0 and timings["click_s"] < 2.0, timings
    assert timings["a_coalesced"] > 2000  # the flood was not queued as 3000 jobs


def test_oversized_upload_is_refused_and_partial_uploads_are_freed(app):
    found: dict = {}

    async def run() -> None:
        async with RawClient(app.port) as c:
            await c.wait_for(lambda m: m["type"] == "GuiUploadButtonMessage", 20)
            # the Review tab's upload button belongs to this client's own GUI
            (client,) = app.server.get_clients().values()
            states = found["states"] = client.gui._current_file_upload_states
            upload = next(m for _, m in c.messages if m["type"] == "GuiUploadButtonMessage")
            size = MAX_UPLOAD_BYTES + 1
            await c.send(
                _messages.FileTransferStartUpload(
                    upload["uuid"], "huge", "big.json", "application/json", size // 524288 + 1, size
                )
            )
            await c.send(_messages.FileTransferPart(upload["uuid"], "huge", 0, b"x" * 524288))
            await c.wait_for(
                lambda m: m["type"] == "NotificationShowMessage" and "Upload refused" in str(m), 5
            )
            assert "huge" not in states
            # a legitimate size, half sent, then the tab closes
            await c.send(
                _messages.FileTransferStartUpload(
                    upload["uuid"], "half", "ok.json", "application/json", 4, 4 * 1024
                )
            )
            await c.send(_messages.FileTransferPart(upload["uuid"], "half", 0, b"{" * 1024))
            await asyncio.sleep(0.3)
            assert "half" in states
        await asyncio.sleep(0.5)

    asyncio.run(run())
    assert not found["states"]  # the half-sent upload was freed on disconnect
    assert any("the limit is" in why for why in app.guard["uploads_refused"])


def _doc(case: str) -> bytes:
    frames = [
        {"frame": i, "joints_mm": [[0.0, 0.0, 400.0]] * 21, "confidence": [1.0] * 21}
        for i in range(6)
    ]
    if case == "frame -1":
        frames[0]["frame"] = -1
    elif case == "joint behind the camera":
        frames[2]["joints_mm"][3] = [0.0, 0.0, -10.0]
    elif case == "not json":
        return b"{nope"
    return json.dumps(
        {"format": "handanno-export", "skeleton": "msra21", "frames": frames}
    ).encode()


@pytest.mark.parametrize("case", ["frame -1", "joint behind the camera", "not json"])
def test_app_import_shows_the_cli_message_and_leaves_the_session_unchanged(app, tmp_path, case):
    """An uploaded bad export gets the same one-line message as ``handanno import`` (the upload's
    name in place of the path), and the session's files are untouched."""
    content = _doc(case)
    path = tmp_path / "bad.json"
    path.write_bytes(content)
    (tmp_path / "copy").mkdir()
    copy = make_session(tmp_path / "copy")  # same shape as the served session
    with pytest.raises(SessionError) as info:
        import_json(copy, path)
    expected = str(info.value).replace(str(path), "bad.json")
    before = {p.name: p.read_bytes() for p in app.session.folder.iterdir() if p.is_file()}

    async def run() -> str:
        async with RawClient(app.port) as c:
            await c.wait_for(lambda m: m["type"] == "GuiUploadButtonMessage", 20)
            upload = next(m for _, m in c.messages if m["type"] == "GuiUploadButtonMessage")
            await c.send(
                _messages.FileTransferStartUpload(
                    upload["uuid"], "t1", "bad.json", "application/json", 1, len(content)
                )
            )
            await c.send(_messages.FileTransferPart(upload["uuid"], "t1", 0, content))
            await c.wait_for(
                lambda m: m["type"] == "NotificationShowMessage" and "Import failed" in str(m), 10
            )
            shown = next(
                m
                for _, m in c.messages
                if m["type"] == "NotificationShowMessage" and "Import failed" in str(m)
            )
            return shown["props"]["body"]

    assert asyncio.run(run()) == expected
    after = {p.name: p.read_bytes() for p in app.session.folder.iterdir() if p.is_file()}
    assert {k: v for k, v in after.items() if k != "session.lock"} == {
        k: v for k, v in before.items() if k != "session.lock"
    }
