"""Journal entries: one JSON line per edit, with a CRC over the session id and the canonical JSON."""

from __future__ import annotations

import json
import zlib
from typing import Any, Literal

from pydantic import BaseModel

# ---------------------------------------------------------------------------------------------
# The session


class JournalEntry(BaseModel):
    seq: int
    time: float
    client: str = "cli"
    #: "do" (a new edit), "undo" (inverse of entry ``target``), "redo" (re-applies entry ``target``)
    action: Literal["do", "undo", "redo"] = "do"
    target: int | None = None
    command: dict[str, Any]
    inverse: dict[str, Any]


def _canonical(data: dict[str, Any]) -> bytes:
    return json.dumps(data, sort_keys=True, separators=(",", ":")).encode()


def entry_checksum(session_id: str, body: dict[str, Any]) -> int:
    """CRC-32 of the session id and the canonical JSON (sorted keys, no spaces) of an entry."""
    return zlib.crc32(session_id.encode() + b"\n" + _canonical(body))


def encode_entry(entry: JournalEntry, session_id: str) -> bytes:
    """One journal line: the entry's canonical JSON plus its ``crc``, newline-terminated."""
    body = entry.model_dump(mode="json")
    return _canonical({**body, "crc": entry_checksum(session_id, body)}) + b"\n"
