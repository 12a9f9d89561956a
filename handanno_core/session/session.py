"""The :class:`Session` object: snapshot + journal replay, execute/undo/redo, results I/O."""

from __future__ import annotations

import contextlib
import errno
import json
import logging
import os
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import ValidationError

from .. import forest
from ..annotation import FrameAnnotation
from ..camera import CameraIntrinsics
from ..fileio import FILE_MODE, atomic_save_npz, atomic_write_bytes, fsync_dir
from ..forest import NO_SELECTION
from ..results import (
    RESULT_KEYS,
    RESULTS_FILE,
    ResultsError,
    read_results,
    result_dtype,
    result_shape,
)
from ..skeleton import Skeleton, get_skeleton
from .commands import (
    Batch,
    Command,
    parse_command,
)
from .files import (
    acquire_session_lock,
    default_writer_command,
    release_session_lock,
)
from .journal import JournalEntry, encode_entry, entry_checksum
from .model import (
    CROPS_FILE,
    CROPS_META_FILE,
    JOURNAL_FILE,
    SESSION_FILE,
    DatasetSpec,
    SelectionModel,
    SessionError,
    SessionModel,
    Settings,
)

log = logging.getLogger(__name__)


def _parse_entry(raw: bytes, session_id: str) -> JournalEntry:
    """One journal line as an entry; ``ValueError``/``ValidationError`` when it is not JSON, not
    an object, fails its checksum or is not an entry."""
    doc = json.loads(raw)
    if not isinstance(doc, dict):
        raise ValueError("not a JSON object")
    crc = doc.pop("crc", None)  # absent in journals written before checksums
    if crc is not None and crc != entry_checksum(session_id, doc):
        raise ValueError(
            "checksum mismatch (a damaged line, or an entry copied from another session's journal)"
        )
    return JournalEntry.model_validate(doc)


def _check_sequence(
    where: str, entry: JournalEntry, previous: int | None, journal_seq: int
) -> None:
    """``SessionError`` unless ``entry`` follows ``previous`` (or, first, the snapshot's
    ``journal_seq``)."""
    if previous is None and entry.seq > journal_seq + 1:
        raise SessionError(
            f"{where}: journal starts at sequence {entry.seq} but {SESSION_FILE} holds "
            f"edits up to {journal_seq} only (entries are missing)"
        )
    if previous is not None and entry.seq != previous + 1:
        raise SessionError(
            f"{where}: sequence {entry.seq} follows {previous} (expected {previous + 1}: "
            "an entry is missing or repeated, e.g. by a second writer)"
        )


def _hand_labels(hands: list[str] | None, breaks: list[int], folder: Path) -> list[str]:
    """Validated hand labels, one per sequence, or ``[]`` (one hand)."""
    labels = [str(h) for h in hands or []]
    if labels and len(labels) != len(breaks) + 1:
        raise SessionError(
            f"{folder}: {len(labels)} hand labels for {len(breaks) + 1} sequences "
            "(one label per sequence between breaks)"
        )
    return labels if len(set(labels)) > 1 else []


def _one_line(exc: Exception) -> str:
    if isinstance(exc, ValidationError):
        err = exc.errors()[0]
        loc = ".".join(str(x) for x in err.get("loc", ()))
        return f"{loc}: {err['msg']}" if loc else str(err["msg"])
    return str(exc).splitlines()[0] if str(exc) else type(exc).__name__


Listener = Callable[[JournalEntry], None]


def _edit_copy(model: SessionModel) -> SessionModel:
    """A copy of ``model`` that commands may edit without touching ``model``: the containers
    commands change in place (``annotations`` and ``review`` items, ``selection.parent`` entries)
    copied one level, the rest shared (commands replace those values, never edit them). O(N) list
    copies instead of a deep copy of every annotation (1.3 s per correction at 76k frames)."""
    selection = model.selection.model_copy(
        update={
            "parent": list(model.selection.parent),
            "reference_frames": list(model.selection.reference_frames),
        }
    )
    return model.model_copy(
        update={
            "annotations": dict(model.annotations),
            "review": dict(model.review),
            "corrections": list(model.corrections),
            "selection": selection,
        }
    )


class Session:
    """A session folder opened for reading and editing. Thread-safe: edits are serialized by a lock."""

    def __init__(self, folder: Path, model: SessionModel):
        self.folder = Path(folder)
        self.model = model
        self.lock = threading.RLock()
        self._journal_file: Any = None
        self._undo: dict[str, list[JournalEntry]] = {}
        self._redo: dict[str, list[JournalEntry]] = {}
        self._listeners: list[Listener] = []
        self._sequence: Any = None
        self._edits_since_snapshot = 0
        self._next_seq = model.journal_seq + 1
        self._lock_key: str | None = None
        #: bytes of the journal that hold acknowledged entries (a torn tail lies beyond)
        self._journal_size = 0
        #: size of the journal file as last seen (with any torn tail); None after a failed rollback
        self._journal_seen: int | None = 0
        #: results written inside :meth:`staged_results` on this thread (not on disk yet)
        self._stage = threading.local()
        #: frame -> (its stored annotation, complete?): :meth:`is_annotated`'s memo
        self._complete: dict[int, tuple[dict[str, Any], bool]] = {}

    # ------------------------------------------------------------------ create / open
    @classmethod
    def create(
        cls,
        folder: str | Path,
        dataset: DatasetSpec,
        frames: int,
        camera: CameraIntrinsics,
        skeleton: str = "msra21",
        sequence_breaks: list[int] | None = None,
        settings: Settings | None = None,
        overwrite: bool = False,
        hands: list[str] | None = None,
    ) -> Session:
        folder = Path(folder)
        if (folder / SESSION_FILE).exists() and not overwrite:
            raise SessionError(f"{folder / SESSION_FILE}: a session already exists here")
        labels = _hand_labels(hands, sequence_breaks or [], folder)
        folder.mkdir(parents=True, exist_ok=True)
        get_skeleton(skeleton)
        model = SessionModel(
            name=folder.name,
            dataset=dataset,
            frames=frames,
            camera=camera,
            skeleton=skeleton,
            sequence_breaks=sequence_breaks or [],
            settings=settings or Settings(),
            session_id=uuid.uuid4().hex,
            hands=labels,
        )
        session = cls(folder, model)
        session.acquire_writer()
        for stale in (JOURNAL_FILE, RESULTS_FILE, CROPS_FILE, CROPS_META_FILE):
            (folder / stale).unlink(missing_ok=True)
        session._journal_size = session._journal_seen = 0
        session.save()
        return session

    @classmethod
    def open(cls, folder: str | Path, *, writer: str | None = None) -> Session:
        """Open a session folder and replay its journal.

        ``writer`` (a command line, e.g. ``"handanno serve demo"``) takes the session's writer lock
        now, failing with :class:`SessionLockedError` while another process holds it; otherwise the
        lock is taken at the first write.
        """
        folder = Path(folder)
        path = folder / SESSION_FILE
        if not folder.is_dir():
            raise SessionError(f"{folder}: no such session folder")
        if not path.exists():
            raise SessionError(
                f"{path}: missing (is {folder} a handanno session? create one with `handanno new`)"
            )
        try:
            model = SessionModel.model_validate_json(path.read_bytes())
        except (ValidationError, ValueError) as exc:
            first = str(exc).splitlines()[:4]
            raise SessionError(f"{path}: corrupt session file: {' '.join(first)}") from exc
        session = cls(folder, model)
        session._replay_journal()
        if writer is not None:
            session.acquire_writer(writer)
        return session

    def _replay_journal(self) -> None:
        """Apply the journal's entries after ``journal_seq``; see the module docstring for checks."""
        path = self.folder / JOURNAL_FILE
        if not path.exists():
            return
        try:
            data = path.read_bytes()
        except OSError as exc:
            raise SessionError(f"{path}: cannot read the journal: {exc}") from exc
        complete = data.rfind(b"\n") + 1
        lines = data[:complete].split(b"\n")[:-1]
        good_end = complete  # end of the acknowledged entries
        entries: list[tuple[int, JournalEntry]] = []
        offset = 0
        for number, raw in enumerate(lines, start=1):
            start, offset = offset, offset + len(raw) + 1
            if not raw.strip():
                continue
            where = f"{path}:{number}"
            last = complete == len(data) and all(not rest.strip() for rest in lines[number:])
            try:
                entry = _parse_entry(raw, self.model.session_id)
            except (ValidationError, ValueError) as exc:
                if last:
                    # A last line that never completed was never acknowledged: cut at next append.
                    good_end = start
                    break
                raise SessionError(f"{where}: corrupt entry: {_one_line(exc)}") from exc
            previous = entries[-1][1].seq if entries else None
            _check_sequence(where, entry, previous, self.model.journal_seq)
            entries.append((number, entry))
        if entries and entries[-1][1].seq < self.model.journal_seq:
            raise SessionError(
                f"{path}: ends at sequence {entries[-1][1].seq} but {SESSION_FILE} has folded in "
                f"edits up to {self.model.journal_seq} (the journal was cut)"
            )
        for number, entry in entries:
            self._replay_entry(f"{path}:{number}", entry)
        if good_end < len(data):
            log.warning(
                "%s: ignoring a torn last entry (%d bytes, never acknowledged); it is cut "
                "before the next edit and kept beside the journal",
                path,
                len(data) - good_end,
            )
        if entries:
            self.model.journal_seq = max(self.model.journal_seq, entries[-1][1].seq)
        self._next_seq = self.model.journal_seq + 1
        self._journal_size, self._journal_seen = good_end, len(data)

    def _replay_entry(self, where: str, entry: JournalEntry) -> None:
        """Check an entry (and its inverse) against the session, apply it if the snapshot does
        not hold it yet, and put it on its client's undo stack."""
        try:
            command = parse_command(entry.command)
            command.check(self)
            parse_command(entry.inverse).check(self)
            if entry.seq > self.model.journal_seq:
                command.apply(self)
        except (ValidationError, ValueError, TypeError, IndexError, KeyError) as exc:
            kind = entry.command.get("kind", "?")
            raise SessionError(
                f"{where}: {kind} entry #{entry.seq} does not fit this session: {_one_line(exc)}"
            ) from exc
        self._track_undo(entry)

    # ------------------------------------------------------------------ derived views
    @property
    def skeleton(self) -> Skeleton:
        return get_skeleton(self.model.skeleton)

    @property
    def camera(self) -> CameraIntrinsics:
        return self.model.camera

    @property
    def num_frames(self) -> int:
        return self.model.frames

    @property
    def reference_frames(self) -> np.ndarray:
        return np.asarray(self.model.selection.reference_frames, dtype=np.int64)

    @property
    def parent(self) -> np.ndarray:
        """``(N,)`` int64 parent forest (:mod:`forest`); all :data:`forest.NO_SELECTION` before a
        selection."""
        p = self.model.selection.parent
        if not p:
            return np.full(self.num_frames, NO_SELECTION, dtype=np.int64)
        return np.asarray(p, dtype=np.int64)

    def annotation(self, frame: int) -> FrameAnnotation | None:
        data = self.model.annotations.get(str(frame))
        if data is None:
            return None
        return FrameAnnotation.from_json(
            data, self.skeleton.num_joints, f"{self.folder / SESSION_FILE} frame {frame}"
        )

    def annotations(
        self, frames: list[int] | np.ndarray | None = None
    ) -> dict[int, FrameAnnotation]:
        keys = sorted(int(k) for k in self.model.annotations)
        if frames is not None:
            wanted = {int(f) for f in frames}
            keys = [k for k in keys if k in wanted]
        out = {}
        for k in keys:
            ann = self.annotation(k)
            if ann is not None:
                out[k] = ann
        return out

    def is_annotated(self, frame: int) -> bool:
        """Every joint of ``frame`` placed or marked outside the image. Memoized per stored annotation (commands replace a
        frame's annotation, never edit it in place), so :meth:`progress` over thousands of
        references parses only what changed."""
        data = self.model.annotations.get(str(frame))
        if data is None:
            return False
        memo = self._complete.get(frame)
        if memo is not None and memo[0] is data:
            return memo[1]
        ann = self.annotation(frame)
        done = ann is not None and bool(ann.complete.all())
        self._complete[frame] = (data, done)
        return done

    def progress(self) -> tuple[int, int]:
        """(annotated references, references)."""
        refs = self.model.selection.reference_frames
        return sum(self.is_annotated(f) for f in refs), len(refs)

    def open_sequence(self):  # -> DepthSequence
        """The session's depth sequence (opened once, lazily)."""
        if self._sequence is None:
            from ..datasets import open_sequence

            spec = self.model.dataset
            try:
                self._sequence = open_sequence(
                    spec.path,
                    format=spec.format,
                    intrinsics=spec.intrinsics,
                    depth_scale_mm=spec.depth_scale_mm,
                )
            except Exception as exc:
                raise SessionError(
                    f"{self.folder / SESSION_FILE}: cannot open dataset {spec.path}: {exc}"
                ) from exc
        return self._sequence

    # ------------------------------------------------------------------ editing
    def subscribe(self, listener: Listener) -> Callable[[], None]:
        """Call ``listener(entry)`` after every acknowledged edit; returns an unsubscribe function."""
        self._listeners.append(listener)
        return lambda: self._listeners.remove(listener) if listener in self._listeners else None

    def execute(self, command: Command | dict[str, Any], client: str = "cli") -> JournalEntry:
        """Validate, journal (durably), then apply one edit. Returns the acknowledged journal entry."""
        if isinstance(command, dict):
            command = parse_command(command)
        with self.lock:
            command.check(self)
            entry = self._commit(command, client, "do", None)
            self._redo[client] = []
        return entry

    def undo(self, client: str = "cli") -> JournalEntry | None:
        return self._step_back_or_forth(client, "undo")

    def redo(self, client: str = "cli") -> JournalEntry | None:
        return self._step_back_or_forth(client, "redo")

    def _step_back_or_forth(self, client: str, kind: str) -> JournalEntry | None:
        """Undo (apply the inverse of) or redo (apply again) the top of ``client``'s stack."""
        with self.lock:
            stack = (self._undo if kind == "undo" else self._redo).get(client)
            if not stack:
                return None
            target = stack[-1]
            command = target.inverse if kind == "undo" else target.command
            return self._commit(parse_command(command), client, kind, target.seq)

    def can_undo(self, client: str = "cli") -> bool:
        return bool(self._undo.get(client))

    def can_redo(self, client: str = "cli") -> bool:
        return bool(self._redo.get(client))

    def _inverse_of(self, command: Command) -> Command:
        if isinstance(command, Batch):
            # Each sub-command's inverse depends on the state left by the ones before it.
            saved = self.model
            self.model = _edit_copy(saved)
            inverses = []
            try:
                for c in command.parsed():
                    inverses.append(c.inverse(self))
                    c.apply(self)
            finally:
                self.model = saved
            return Batch(commands=[i.model_dump() for i in reversed(inverses)])
        return command.inverse(self)

    def _commit(
        self, command: Command, client: str, action: str, target: int | None
    ) -> JournalEntry:
        inverse = self._inverse_of(command)
        entry = JournalEntry(
            seq=self._next_seq,
            time=time.time(),
            client=client,
            action=action,  # type: ignore[arg-type]
            target=target,
            command=command.model_dump(),
            inverse=inverse.model_dump(),
        )
        self._append_journal(entry)  # durable before anything is acknowledged
        self._next_seq += 1
        command.apply(self)
        self.model.journal_seq = entry.seq
        self._track_undo(entry)
        self._edits_since_snapshot += 1
        if self._edits_since_snapshot >= 200:
            try:
                self.save()
            except (OSError, SessionError) as exc:  # the edit is in the journal: still saved
                log.warning("%s: snapshot deferred: %s", self.folder / SESSION_FILE, exc)
        for listener in list(self._listeners):
            try:
                listener(entry)
            except Exception:  # a broken view must not break editing
                pass
        return entry

    def _track_undo(self, entry: JournalEntry) -> None:
        undo = self._undo.setdefault(entry.client, [])
        redo = self._redo.setdefault(entry.client, [])
        if entry.action == "do":
            undo.append(entry)
            redo.clear()
        elif entry.action == "undo":
            if undo:
                redo.append(undo.pop())
        elif entry.action == "redo":
            if redo:
                undo.append(redo.pop())

    def _journal_fd(self) -> int:
        """The journal opened for appending, its torn tail (if any) cut first. Under ``self.lock``."""
        path = self.folder / JOURNAL_FILE
        if self._journal_file is None:
            self.acquire_writer()
            if not self.model.session_id:  # a session from before checksums: give it an id first
                self.model.session_id = uuid.uuid4().hex
                self.save()
            try:
                created = not path.exists()
                self._journal_file = os.open(
                    path, os.O_WRONLY | os.O_APPEND | os.O_CREAT | os.O_CLOEXEC, FILE_MODE
                )
                if created:
                    fsync_dir(self.folder)  # the new journal's name survives a power loss too
            except OSError as exc:
                raise SessionError(f"{path}: cannot open the edit journal: {exc}") from exc
        fd = self._journal_file
        size = os.fstat(fd).st_size
        if size != self._journal_size:
            if size < self._journal_size or (
                self._journal_seen is not None and size != self._journal_seen
            ):
                raise SessionError(
                    f"{path}: changed by another writer since this session was opened "
                    f"({size} bytes, expected {self._journal_size}); reopen the session"
                )
            self._cut_torn_tail(fd, size)
        return fd

    def _cut_torn_tail(self, fd: int, size: int) -> None:
        """Move the bytes after the last acknowledged entry to ``journal.jsonl.torn-<time>``."""
        path = self.folder / JOURNAL_FILE
        with open(path, "rb") as f:
            f.seek(self._journal_size)
            torn = f.read(size - self._journal_size)
        stamp = time.strftime("%Y%m%dT%H%M%S") + f"-{time.time_ns() % 1_000_000_000:09d}"
        keep = path.with_name(f"{JOURNAL_FILE}.torn-{stamp}")
        try:
            atomic_write_bytes(keep, torn)
            os.ftruncate(fd, self._journal_size)
            os.fsync(fd)
        except OSError as exc:
            raise SessionError(f"{path}: cannot cut the torn last entry: {exc}") from exc
        self._journal_seen = self._journal_size
        log.warning("%s: cut a torn last entry (%d bytes), kept in %s", path, len(torn), keep.name)

    def _append_journal(self, entry: JournalEntry) -> None:
        """Append one entry durably: one ``write`` of the whole line, then fsync.

        If either fails, the file is truncated back to its previous size, so the refused edit can
        never be glued to the next one or resurface on replay.
        """
        path = self.folder / JOURNAL_FILE
        fd = self._journal_fd()
        line = encode_entry(entry, self.model.session_id)
        before = self._journal_size
        try:
            written = os.write(fd, line)
            if written != len(line):
                raise OSError(errno.ENOSPC, f"short write ({written} of {len(line)} bytes)")
            os.fsync(fd)
        except OSError as exc:
            try:
                os.ftruncate(fd, before)
                os.fsync(fd)
                self._journal_seen = before
            except OSError:
                self._journal_seen = None  # cut whatever lies beyond before the next append
            raise SessionError(f"{path}: edit NOT saved, cannot write the journal: {exc}") from exc
        self._journal_size = self._journal_seen = before + len(line)

    # ------------------------------------------------------------------ the writer lock
    def acquire_writer(self, command: str | None = None) -> Session:
        """Take this session's writer lock (see :func:`acquire_session_lock`) and cut a torn tail.

        Called by ``serve`` and every CLI command that writes, and implicitly by the first write.
        Raises :class:`SessionLockedError` naming the other writer's PID and command.
        """
        with self.lock:
            if self._lock_key is None:
                self._lock_key = acquire_session_lock(
                    self.folder, command or default_writer_command()
                )
                if self._journal_seen != self._journal_size and self._journal_file is None:
                    self._journal_fd()  # cut the torn tail now, before anything is appended
        return self

    @property
    def is_writer(self) -> bool:
        return self._lock_key is not None

    # ------------------------------------------------------------------ bulk state (not journaled edits)
    def set_selection(self, selection: dict[str, Any]) -> None:
        """Store a new reference selection (from ``handanno select``); snapshot immediately.
        ``ValueError`` unless its parents are a forest rooted exactly at its references
        (:func:`handanno_core.forest.validate`)."""
        with self.lock:
            parent = list(map(int, selection["parent"]))
            if len(parent) != self.num_frames:
                raise ValueError(
                    f"selection has {len(parent)} parents for {self.num_frames} frames"
                )
            refs = sorted(map(int, selection["reference_frames"]))
            try:
                forest.validate(np.asarray(parent), np.asarray(refs, dtype=np.int64))
            except ValueError as exc:
                raise ValueError(f"selection for {self.folder}: {exc}") from None
            self.model.selection = SelectionModel(
                strategy=selection.get("strategy"),
                reference_frames=refs,
                parent=parent,
                threshold=selection.get("threshold"),
                ref_fraction=selection.get("ref_fraction"),
                skipped_frames=sorted(map(int, selection.get("skipped_frames", []))),
            )
            self.model.corrections = []
            self.save()

    def set_bone_lengths(
        self,
        bone_lengths_mm: np.ndarray | None,
        pinned: bool | None = None,
        hands: dict[str, np.ndarray] | None = None,
    ) -> None:
        """Store the session's bone lengths ``(B,)`` mm and, with several hands, every hand's
        ``{label: (B,)}`` (``hands`` None: the per-hand lengths are cleared, so every hand
        uses ``bone_lengths_mm``)."""
        with self.lock:
            self.model.bone_lengths_mm = (
                None if bone_lengths_mm is None else [float(x) for x in bone_lengths_mm]
            )
            self.model.hand_bone_lengths_mm = {
                str(k): [float(x) for x in v] for k, v in (hands or {}).items()
            }
            if pinned is not None:
                self.model.bones_pinned = pinned
            self.save()

    def set_click_noise(self, noise_px: float | None, given: bool = False) -> None:
        """Record the click noise (px) the last lift's refit used (``given``: not estimated)."""
        with self.lock:
            self.model.lift_click_noise_px = None if noise_px is None else float(noise_px)
            self.model.lift_click_noise_given = bool(given)
            self.save()

    def click_noise_text(self) -> str | None:
        """``"clicks: 1.8 px noise (estimated by the last lift)"``, or None before one."""
        noise = self.model.lift_click_noise_px
        if noise is None:
            return None
        how = "given to" if self.model.lift_click_noise_given else "estimated by"
        return f"clicks: {noise:.1f} px noise ({how} the last lift)"

    # ------------------------------------------------------------------ hands
    @property
    def hand_names(self) -> list[str]:
        """The distinct hand labels in first-appearance order (``[""]``: one hand)."""
        return list(dict.fromkeys(self.model.hands)) or [""]

    def hand_of_frame(self) -> np.ndarray:
        """``(N,)`` int: each frame's hand, an index into :attr:`hand_names` (all 0: one hand)."""
        n = self.num_frames
        labels = self.model.hands
        if not labels:
            return np.zeros(n, dtype=np.int64)
        if len(labels) != len(self.model.sequence_breaks) + 1:
            raise SessionError(
                f"{self.folder / SESSION_FILE}: {len(labels)} hand labels for "
                f"{len(self.model.sequence_breaks) + 1} sequences"
            )
        names = {h: i for i, h in enumerate(self.hand_names)}
        per_sequence = np.asarray([names[h] for h in labels], dtype=np.int64)
        sequence = np.searchsorted(
            np.asarray(self.model.sequence_breaks, dtype=np.int64), np.arange(n), side="right"
        )
        return per_sequence[sequence]

    def frame_bone_lengths(self) -> np.ndarray | None:
        """The bone lengths the stages use: ``(B,)`` mm when every frame has the same (one hand,
        or pinned bones), else ``(N, B)`` mm, each frame its hand's; None before the lift."""
        if self.model.bone_lengths_mm is None:
            return None
        table = self.model.hand_bone_lengths_mm
        names = self.hand_names
        if len(names) < 2 or not table:
            return np.asarray(self.model.bone_lengths_mm, dtype=np.float64)
        rows = np.asarray(
            [table.get(h, self.model.bone_lengths_mm) for h in names], dtype=np.float64
        )
        if np.all(rows == rows[:1]):
            return rows[0]
        return rows[self.hand_of_frame()]

    def bone_lengths_of(self, frame: int) -> list[float] | None:
        """Frame ``frame``'s hand's bone lengths (mm), else the session's (None before the lift)."""
        hands = self.model.hands
        if hands and self.model.hand_bone_lengths_mm:
            seq = int(np.searchsorted(self.model.sequence_breaks, int(frame), side="right"))
            own = self.model.hand_bone_lengths_mm.get(hands[seq])
            if own is not None:
                return own
        return self.model.bone_lengths_mm

    def save(self) -> None:
        """Write the snapshot atomically (the journal stays the source of truth for later edits)."""
        with self.lock:
            self.acquire_writer()
            try:
                atomic_write_bytes(
                    self.folder / SESSION_FILE, self.model.model_dump_json(indent=1).encode()
                )
            except OSError as exc:
                raise SessionError(f"{self.folder / SESSION_FILE}: cannot write: {exc}") from exc
            self._edits_since_snapshot = 0

    def close(self) -> None:
        """Snapshot (if this object wrote), close the journal and release the writer lock."""
        with self.lock:
            try:
                if self._lock_key is not None:
                    self.save()
            finally:
                if self._journal_file is not None:
                    os.close(self._journal_file)
                    self._journal_file = None
                if self._lock_key is not None:
                    release_session_lock(self._lock_key)
                    self._lock_key = None

    # ------------------------------------------------------------------ results
    def _expected_result_shape(self, key: str) -> tuple[int, ...]:
        return result_shape(key, self.num_frames, self.skeleton.num_joints)

    def load_results(self) -> dict[str, np.ndarray]:
        """Results arrays (:func:`~handanno_core.results.read_results`; a file without
        ``source`` gets it from the selection's parent forest); inside :meth:`staged_results`
        this thread sees its staged arrays. A corrupt or foreign ``results.npz`` raises
        :class:`SessionError` naming the file."""
        try:
            out = read_results(
                self.folder / RESULTS_FILE,
                self.num_frames,
                self.skeleton.num_joints,
                parent=self.parent,
            )
        except ResultsError as exc:
            raise SessionError(str(exc)) from exc
        staged = getattr(self._stage, "arrays", None)
        if staged:
            out.update({k: v.copy() for k, v in staged.items()})
        return out

    def save_results(self, **arrays: np.ndarray) -> None:
        """Update some result arrays (others kept) in one atomic replace of ``results.npz``."""
        for key, value in arrays.items():
            if key not in RESULT_KEYS or np.shape(value) != self._expected_result_shape(key):
                raise ValueError(
                    f"results: {key} of shape {np.shape(value)} does not fit this session "
                    f"(keys {RESULT_KEYS})"
                )
        staged = getattr(self._stage, "arrays", None)
        if staged is not None:
            staged.update({k: np.array(v, dtype=result_dtype(k)) for k, v in arrays.items()})
            return
        with self.lock:
            self.acquire_writer()
            current = self.load_results()
            current.update({k: np.asarray(v, dtype=result_dtype(k)) for k, v in arrays.items()})
            try:
                atomic_save_npz(self.folder / RESULTS_FILE, current)
            except OSError as exc:
                raise SessionError(f"{self.folder / RESULTS_FILE}: cannot write: {exc}") from exc

    @contextlib.contextmanager
    def staged_results(self) -> Iterator[dict[str, np.ndarray]]:
        """Stage this thread's :meth:`save_results` in memory; write them in one replace at the end.

        A job that saves several stages (the app's propagate, then refine) runs inside this block,
        so ``results.npz`` holds either everything from before the job or everything after it:
        an exception (cancel) or a kill leaves the file exactly as it was.
        """
        if getattr(self._stage, "arrays", None) is not None:
            raise RuntimeError("staged_results blocks do not nest")
        self._stage.arrays = {}
        try:
            yield self._stage.arrays
            staged = self._stage.arrays
        finally:
            self._stage.arrays = None
        if staged:
            self.save_results(**staged)

    def summary(self) -> str:
        done, total = self.progress()
        sel = self.model.selection
        lines = [
            f"session {self.model.name} ({self.folder})",
            f"  dataset: {self.model.dataset.format} {self.model.dataset.path}, {self.num_frames} frames",
            f"  skeleton: {self.model.skeleton}, camera f=({self.camera.fx:g}, {self.camera.fy:g})",
            f"  selection: {sel.strategy or 'none'}, references: {len(sel.reference_frames)} of {self.num_frames}",
            f"  annotated references: {done} of {total}; corrections: {len(self.model.corrections)}",
        ]
        if self.model.hands:
            names = self.hand_names
            lines.append(
                f"  hands: {len(names)} ({', '.join(names[:10])}{' ...' if len(names) > 10 else ''}), "
                f"own bone lengths per hand{'' if self.model.hand_bone_lengths_mm else ' after the lift'}"
            )
        noise = self.click_noise_text()
        if noise:
            lines.append(f"  {noise}")
        return "\n".join(lines)

    def __enter__(self) -> Session:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
