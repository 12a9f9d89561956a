"""Session folders on disk: name resolution and the one-writer advisory lock."""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import os
import re
import shutil
import sys
import threading
import time
from pathlib import Path
from typing import Any

from ..fileio import FILE_MODE
from .model import LOCK_FILE, SessionError, SessionLockedError

# ---------------------------------------------------------------------------------------------
# Atomic file helpers


# ---------------------------------------------------------------------------------------------
# One writer per session: an advisory lock that dies with its process

_held_locks: dict[str, list[Any]] = {}  # realpath of the lock file -> [fd, holders]
_held_guard = threading.Lock()


def _lock_owner(fd: int) -> str:
    try:
        owner = json.loads(os.pread(fd, 4096, 0) or b"{}")
        since = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(float(owner["started"])))
        return f"PID {int(owner['pid'])} ({owner['command']}, since {since})"
    except (OSError, ValueError, KeyError, TypeError):
        return "another process (owner unknown)"


def acquire_session_lock(folder: Path, command: str) -> str:
    """Take the writer lock of the session ``folder`` for this process; returns its key.

    Several :class:`Session` objects of one process share the lock (the per-session ``RLock``
    serializes them); another process gets :class:`SessionLockedError` naming the owner's PID,
    command and start time. The lock is ``flock`` on ``session.lock``: it dies with its process.
    """
    path = Path(folder) / LOCK_FILE
    key = os.path.realpath(path)
    with _held_guard:
        held = _held_locks.get(key)
        if held is not None:
            held[1] += 1
            return key
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, FILE_MODE)
        except OSError as exc:
            raise SessionError(f"{path}: cannot create the session lock: {exc}") from exc
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            owner = _lock_owner(fd)
            os.close(fd)
            if exc.errno not in (errno.EAGAIN, errno.EACCES):
                raise SessionError(f"{path}: cannot lock the session: {exc}") from exc
            raise SessionLockedError(
                f"{Path(folder)}: session is being written by {owner}; "
                "stop that process first (one writer per session)"
            ) from None
        owner = {"pid": os.getpid(), "command": command, "started": time.time()}
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps(owner).encode(), 0)
        _held_locks[key] = [fd, 1]
        return key


def release_session_lock(key: str) -> None:
    with _held_guard:
        held = _held_locks.get(key)
        if held is None:
            return
        held[1] -= 1
        if held[1] <= 0:
            del _held_locks[key]
            with contextlib.suppress(OSError):
                os.ftruncate(held[0], 0)
            os.close(held[0])  # closing the only descriptor releases the flock


def remove_session_folder(folder: Path, command: str) -> None:
    """Delete the session ``folder`` if it exists (a bench run's session about to be made again),
    unless another process holds its writer lock: :class:`SessionLockedError` naming it. Two bench
    runs given the same work folder deleted each other's sessions mid-run before this check."""
    folder = Path(folder)
    if not folder.exists():
        return
    if (folder / LOCK_FILE).exists():
        release_session_lock(acquire_session_lock(folder, command))
    shutil.rmtree(folder)


def copy_session_folder(folder: Path, to: Path, command: str) -> None:
    """Copy the closed session ``folder`` to ``to``, replacing it (:func:`remove_session_folder`:
    not while another process writes it); symlinks (a shared crop cache) stay symlinks, the lock
    file stays behind."""
    remove_session_folder(to, command)
    shutil.copytree(folder, to, symlinks=True, ignore=shutil.ignore_patterns(LOCK_FILE))


def default_writer_command() -> str:
    """How this process names itself in a lock: ``handanno serve demo`` style."""
    argv = list(sys.argv) or ["python"]
    argv[0] = "handanno" if argv[0].endswith(("handanno", "cli.py")) else Path(argv[0]).name
    return " ".join(argv)[:200]


_SAFE_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,127}$")


def safe_session_path(name: str, sessions_dir: str | Path) -> Path:
    """Resolve a session *name* from a user (e.g. in the app) under ``sessions_dir``, refusing path tricks."""
    if not _SAFE_NAME.match(name) or ".." in name:
        raise SessionError(
            f"invalid session name {name!r}: use letters, digits, '.', '_' or '-' (no path separators)"
        )
    base = Path(sessions_dir).resolve()
    path = (base / name).resolve()
    if path.parent != base:
        raise SessionError(f"session {name!r} resolves outside the sessions folder {base}")
    return path


def resolve_session(session: str | Path, sessions_dir: str | Path = "sessions") -> Path:
    """CLI rule: a path (contains a separator or exists) is used as is; a bare name lives in ``sessions_dir``."""
    s = str(session)
    if s.strip(".") == "":  # ".", "..": never a session name, and not a session folder either
        raise SessionError(f"invalid session {s!r}: give a session name or a path to its folder")
    if os.sep in s or "/" in s or Path(s).exists():
        return Path(s)
    return safe_session_path(s, sessions_dir)
