"""What one browser may ask of the server (issue 16): no share tunnel, bounded uploads, a fair share
of the server's time.

viser trusts its websocket clients: any of them can send ``ShareUrlRequest`` (viser then forks a
process that opens a public tunnel to ``share.viser.studio``), start uploads of any declared size,
and queue callbacks as fast as it can send messages, all handled first-come first-served. Three
small hooks on a :class:`viser.ViserServer` bound that:

* :func:`refuse_share_url` removes viser's share handlers (and ``request_share_url`` itself), so no
  tunnel can start, and logs each refused request;
* :func:`cap_uploads` refuses an upload that declares more than ``max_bytes`` (or more parts than
  that size needs, or a third concurrent upload from one browser), drops parts that would overrun
  the declared size or come from another client, and tells the browser why; viser already frees a
  client's partial uploads when it disconnects;
* :class:`ClientRateLimiter` gives every client token buckets for the messages that make the
  server work (clicks and GUI updates; drag streams apart, with more room). A client over its
  budget has its messages coalesced per control (the newest value is kept and delivered as tokens
  refill, so a slider or a gizmo always ends where the user left it; a flood of clicks on one
  button becomes one click), and beyond 64 distinct waiting messages dropped, so a flood from one
  browser cannot queue work ahead of everybody else.

Only private viser attributes of version 1.1 are touched (``_websock_server``, the GUI API's upload
handlers); each hook checks they exist and fails loudly at start-up otherwise.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import viser
from viser import _messages

log = logging.getLogger(__name__)

#: Largest upload accepted (bytes): a JSON export of 76k frames x 21 joints is about 60 MB.
MAX_UPLOAD_BYTES = 64 * 1024 * 1024
#: Concurrent uploads per browser.
MAX_UPLOADS_PER_CLIENT = 2
#: viser's upload part size is 512 KiB; a part count above size / 1 KiB is not a real upload.
_MIN_PART_BYTES = 1024

#: Messages a browser sends continuously or that are bounded elsewhere: never rate limited.
_UNMETERED = (
    _messages.ViewerCameraMessage,
    _messages.FileTransferPart,  # bounded by cap_uploads
    _messages.FileTransferPartAck,
)


def _websock(server: viser.ViserServer) -> Any:
    ws = getattr(server, "_websock_server", None)
    if ws is None or not hasattr(ws, "_incoming_handlers"):
        raise RuntimeError("app.guard: this viser version has no _websock_server handlers")
    return ws


def refuse_share_url(server: viser.ViserServer, refused: list[int] | None = None) -> None:
    """Make viser's share-URL request a no-op: no tunnel process can start from a browser.

    ``refused`` (optional) collects the client id of every refused request (tests).
    """
    ws = _websock(server)
    for cls in (_messages.ShareUrlRequest, _messages.ShareUrlDisconnect):
        ws._incoming_handlers.pop(cls, None)

    def on_request(client_id: int, message: Any) -> None:
        if refused is not None:
            refused.append(int(client_id))
        log.warning("share-URL request from client %s refused (no public tunnels)", client_id)

    ws.register_handler(_messages.ShareUrlRequest, on_request)

    def no_tunnel(*args: Any, **kwargs: Any) -> None:
        raise RuntimeError("handanno never opens a share tunnel")

    server.request_share_url = no_tunnel  # type: ignore[method-assign]


def cap_uploads(
    server: viser.ViserServer,
    max_bytes: int = MAX_UPLOAD_BYTES,
    max_per_client: int = MAX_UPLOADS_PER_CLIENT,
    refused: list[str] | None = None,
) -> None:
    """Refuse uploads above ``max_bytes`` before buffering a byte; see the module docstring.

    Applies to the server-wide GUI and to every client's own GUI (upload buttons made with
    ``client.gui`` are served by that client's connection).
    """
    _websock(server)
    _cap_gui_uploads(server.gui, server, max_bytes, max_per_client, refused)
    server.on_client_connect(
        lambda client: _cap_gui_uploads(client.gui, server, max_bytes, max_per_client, refused)
    )


def _cap_gui_uploads(
    gui: Any,
    server: viser.ViserServer,
    max_bytes: int,
    max_per_client: int,
    refused: list[str] | None,
) -> None:
    ws = gui._websock_interface
    states: dict[str, dict] = gui._current_file_upload_states
    start, part = gui._handle_file_transfer_start, gui._handle_file_transfer_part
    ws.unregister_handler(_messages.FileTransferStartUpload, start)
    ws.unregister_handler(_messages.FileTransferPart, part)

    def refuse(client_id: int, why: str) -> None:
        if refused is not None:
            refused.append(why)
        log.warning("upload from client %s refused: %s", client_id, why)
        client = server.get_clients().get(int(client_id))
        if client is not None:
            client.add_notification("Upload refused", why, color="red", auto_close_seconds=8.0)

    def on_start(client_id: int, message: Any) -> None:
        size, parts = int(message.size_bytes), int(message.part_count)
        mine = sum(1 for s in list(states.values()) if s["client_id"] == client_id)
        if not 0 <= size <= max_bytes:
            refuse(client_id, f"{message.filename!r}: {size} bytes; the limit is {max_bytes} bytes")
        elif not 0 <= parts <= max(1, size // _MIN_PART_BYTES + 1):
            refuse(client_id, f"{message.filename!r}: {parts} parts for {size} bytes")
        elif mine >= max_per_client:
            refuse(client_id, f"{message.filename!r}: {mine} uploads already in progress")
        else:
            start(client_id, message)

    def on_part(client_id: int, message: Any) -> None:
        state = states.get(message.transfer_uuid)
        if state is None or state["client_id"] != client_id:
            return  # unknown transfer, or another client's: ignored
        if state["transferred_bytes"] + len(message.content) > state["total_bytes"]:
            states.pop(message.transfer_uuid, None)  # free what was buffered
            refuse(client_id, f"{state['filename']!r}: more bytes than declared; upload dropped")
            return
        part(client_id, message)

    ws.register_handler(_messages.FileTransferStartUpload, on_start)
    ws.register_handler(_messages.FileTransferPart, on_part)


#: Messages a browser streams while the user drags (60 Hz): metered by their own, roomier bucket.
_STREAMS = (
    _messages.TransformControlsUpdateMessage,
    _messages.TransformControlsDragStartMessage,
    _messages.TransformControlsDragEndMessage,
    _messages.SceneNodeDragMessage,
)
#: Most distinct messages one client may have waiting; beyond, its messages are dropped.
MAX_PENDING = 64


def _coalesce_key(message: Any) -> tuple:
    """Messages with equal keys are interchangeable but for their latest content."""
    if isinstance(message, _messages.GuiUpdateMessage):
        return ("gui", message.uuid, tuple(sorted(message.updates)))
    if isinstance(message, _messages.SceneNodeDragMessage):
        return ("drag", message.name, message.instance_index, message.phase)
    ident = getattr(message, "uuid", None) or getattr(message, "name", None)
    return (type(message).__name__, ident)


@dataclass
class _Bucket:
    rate: float
    burst: float
    tokens: float = 0.0
    last: float = field(default_factory=time.monotonic)

    def __post_init__(self) -> None:
        self.tokens = self.burst

    def take(self) -> bool:
        now = time.monotonic()
        self.tokens = min(self.burst, self.tokens + (now - self.last) * self.rate)
        self.last = now
        if self.tokens >= 1.0:
            self.tokens -= 1.0
            return True
        return False


@dataclass
class _Client:
    clicks: _Bucket
    drags: _Bucket
    pending: OrderedDict = field(default_factory=OrderedDict)
    draining: bool = False
    dropped: int = 0
    coalesced: int = 0


class ClientRateLimiter:
    """Per-client token buckets in front of viser's message dispatch; see the module docstring.

    Discrete messages (GUI updates, clicks): ``rate_per_s=30``, ``burst=60`` -- a human clicks at
    most ~10 times a second. Drag streams (gizmos, scene-node drags; viser sends them at up to
    60 Hz): ``drag_rate_per_s=120``, ``drag_burst=240``. Over budget, messages wait, coalesced per
    control (:func:`_coalesce_key`: the newest value wins, a drag's start/update/end stay apart),
    and are delivered in order as tokens refill; more than :data:`MAX_PENDING` distinct waiting
    messages are dropped.
    """

    def __init__(
        self,
        server: viser.ViserServer,
        rate_per_s: float = 30.0,
        burst: int = 60,
        drag_rate_per_s: float = 120.0,
        drag_burst: int = 240,
    ):
        self.rates = (float(rate_per_s), float(burst), float(drag_rate_per_s), float(drag_burst))
        self._ws = _websock(server)
        self._clients: dict[int, _Client] = {}
        # viser hands every message to two dispatchers: the server's (server-wide GUI and scene)
        # and the client connection's (that client's own GUI, e.g. handanno's panels). Metered
        # messages are decided once, in the connection's dispatcher, which then calls both.
        self._server_inner: Callable[..., Any] = self._ws._handle_incoming_message
        self._ws._handle_incoming_message = self._server_level  # instance attribute: viser calls it
        self._ws.on_client_connect(self._hook_connection)
        self._ws.on_client_disconnect(lambda conn: self._clients.pop(conn.client_id, None))

    def _hook_connection(self, conn: Any) -> None:
        client_inner = conn._handle_incoming_message

        async def handle(client_id: int, message: Any) -> None:
            await self._metered(client_id, message, client_inner)

        conn._handle_incoming_message = handle

    async def _server_level(self, client_id: int, message: Any) -> None:
        if isinstance(message, _UNMETERED):
            await self._server_inner(client_id, message)
        # metered messages reach the server's dispatcher through _metered

    def stats(self, client_id: int) -> tuple[int, int]:
        """(dropped, coalesced) messages of ``client_id`` so far."""
        c = self._clients.get(int(client_id))
        return (c.dropped, c.coalesced) if c is not None else (0, 0)

    def _bucket(self, c: _Client, message: Any) -> _Bucket:
        return c.drags if isinstance(message, _STREAMS) else c.clicks

    async def _metered(self, client_id: int, message: Any, client_inner: Callable) -> None:
        async def dispatch(m: Any) -> None:
            await self._server_inner(client_id, m)
            await client_inner(client_id, m)

        if isinstance(message, _UNMETERED):
            await client_inner(client_id, message)
            return
        c = self._clients.get(client_id)
        if c is None:
            rate, burst, drag_rate, drag_burst = self.rates
            c = self._clients[client_id] = _Client(
                _Bucket(rate, burst), _Bucket(drag_rate, drag_burst)
            )
        if not c.pending and self._bucket(c, message).take():
            await dispatch(message)
            return
        key = _coalesce_key(message)
        if key in c.pending:
            c.coalesced += 1
            old = c.pending.pop(key)
            if isinstance(message, _messages.GuiUpdateMessage):
                message = _messages.GuiUpdateMessage(
                    message.uuid, {**old.updates, **message.updates}
                )
        elif len(c.pending) >= MAX_PENDING:
            c.dropped += 1
            return
        c.pending[key] = message
        if not c.draining:
            c.draining = True
            asyncio.get_running_loop().create_task(self._drain(client_id, c, dispatch))

    async def _drain(self, client_id: int, c: _Client, dispatch: Callable) -> None:
        try:
            while c.pending and self._clients.get(client_id) is c:
                key = next(iter(c.pending))
                bucket = self._bucket(c, c.pending[key])
                if not bucket.take():
                    await asyncio.sleep(1.0 / bucket.rate)
                    continue
                await dispatch(c.pending.pop(key))
        finally:
            c.draining = False


def harden(server: viser.ViserServer) -> dict[str, Any]:
    """All three hooks with their defaults; returns what tests inspect (refusals, the limiter)."""
    share: list[int] = []
    uploads: list[str] = []
    refuse_share_url(server, share)
    cap_uploads(server, refused=uploads)
    return {
        "share_refused": share,
        "uploads_refused": uploads,
        "limiter": ClientRateLimiter(server),
    }
