"""Durable file writes shared by the session, its results and the exports.

Whole files are replaced atomically (a temporary file in the same folder, fsynced, ``os.replace``,
then the folder fsynced), so a reader sees the old or the new file, never a part, whatever instant
a crash or a kill hits. Every file gets :data:`FILE_MODE`.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

import numpy as np


def _file_mode() -> int:
    umask = os.umask(0)
    os.umask(umask)
    return 0o666 & ~umask


#: Mode of every file a session writes (journal, snapshot, results, caches, lock): 0666 less the
#: umask at import, so a session's files never differ in who may read them (mkstemp's 0600 is
#: widened to it).
FILE_MODE = _file_mode()


def fsync_dir(folder: Path) -> None:
    """Make a rename or a new file in ``folder`` durable (a no-op where directories cannot be opened)."""
    try:
        fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Replace ``path`` by ``data`` in one step (temporary file, fsync, ``os.replace``), mode FILE_MODE."""
    _atomic_write(Path(path), lambda f: f.write(data), ".tmp")


def _atomic_write(path: Path, write, suffix: str) -> None:
    """Call ``write(f)`` on a temporary file beside ``path``, fsync it and replace ``path``."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=suffix)
    try:
        with os.fdopen(fd, "wb") as f:
            os.fchmod(f.fileno(), FILE_MODE)
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
        fsync_dir(path.parent)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_save_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """Write ``arrays`` as an ``.npz`` that replaces ``path`` only once complete and fsynced."""
    _atomic_write(Path(path), lambda f: np.savez(f, **arrays), ".npz")


def read_json_object(path: Path, what: str) -> dict:
    """The JSON object (a dict) in ``path``; ``ValueError`` naming the file and ``what`` it holds
    when it cannot be read, is not JSON or is not an object."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: cannot read {what}: {exc}") from exc
    if not isinstance(data, dict):
        raise ValueError(f"{path}: invalid {what}: expected a JSON object")
    return data
