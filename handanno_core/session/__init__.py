"""An annotation session is a folder; this module is its data model, used by the CLI and the app alike.

Layout of ``sessions/<name>/``:

* ``session.json`` - :class:`SessionModel` snapshot (dataset, camera, skeleton, settings, selection,
  annotations, review state) plus ``journal_seq``, the last journal entry folded into the snapshot;
* ``journal.jsonl`` - every edit, one JSON line each, appended, flushed and fsynced *before* the edit
  is acknowledged; reopening replays the entries after ``journal_seq``;
* ``crops.npy`` / ``crops_meta.npz`` - the crop cache (memory-mapped) and its geometry;
* ``results.npz`` - lifted / propagated / refined joints and confidences (derived, recomputable).

Every edit is a small command object (SLEAP style) with ``apply`` and an ``inverse`` computed from
the state it replaces, so undo and redo are journal entries too and a crash at any instant loses no
acknowledged edit. Writes of whole files are atomic (temporary file + ``os.replace``).

Journal integrity: each entry is one ``os.write`` of the whole line, fsynced; a failed
write or fsync truncates the file back to its previous size, so a refused edit never resurfaces.
Each line carries ``crc`` (CRC-32 of the session id and the canonical JSON of the entry), and the
sequence numbers must be continuous: replay names ``journal.jsonl:LINE: reason`` for a corrupt,
foreign (another session's) or out-of-range entry. A torn last line (a write that never completed,
so never acknowledged) is cut before the next append and its bytes kept beside the journal as
``journal.jsonl.torn-<time>``. One process writes a session at a time: the first write (or
:meth:`Session.acquire_writer`) takes an advisory ``flock`` on ``session.lock`` that names the owner
(PID, command, start time) and dies with the process, so a stale lock is taken over naturally.
"""

from ..fileio import FILE_MODE, atomic_save_npz, atomic_write_bytes
from ..results import RESULTS_FILE
from .commands import (
    Batch,
    Command,
    SetDepthOrder,
    SetFrameAnnotation,
    SetJoint2D,
    SetJoint3D,
    SetJointState,
    SetOutside,
    SetReference,
    SetReview,
    SetVisibility,
    parse_command,
)
from .files import (
    acquire_session_lock,
    copy_session_folder,
    default_writer_command,
    release_session_lock,
    remove_session_folder,
    resolve_session,
    safe_session_path,
)
from .journal import JournalEntry, encode_entry, entry_checksum
from .model import (
    CROPS_FILE,
    CROPS_META_FILE,
    JOURNAL_FILE,
    LOCK_FILE,
    SESSION_FILE,
    DatasetSpec,
    SelectionModel,
    SessionError,
    SessionLockedError,
    SessionModel,
    Settings,
)
from .session import Listener, Session

__all__ = [
    "Batch",
    "CROPS_FILE",
    "CROPS_META_FILE",
    "Command",
    "DatasetSpec",
    "FILE_MODE",
    "JOURNAL_FILE",
    "JournalEntry",
    "LOCK_FILE",
    "Listener",
    "RESULTS_FILE",
    "SESSION_FILE",
    "SelectionModel",
    "Session",
    "SessionError",
    "SessionLockedError",
    "SessionModel",
    "SetDepthOrder",
    "SetFrameAnnotation",
    "SetJoint2D",
    "SetJoint3D",
    "SetJointState",
    "SetOutside",
    "SetReference",
    "SetReview",
    "SetVisibility",
    "Settings",
    "acquire_session_lock",
    "atomic_save_npz",
    "atomic_write_bytes",
    "default_writer_command",
    "encode_entry",
    "copy_session_folder",
    "entry_checksum",
    "parse_command",
    "release_session_lock",
    "remove_session_folder",
    "resolve_session",
    "safe_session_path",
]
