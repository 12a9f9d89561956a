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
"""

from __future__ import annotations

import os
import re
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import BaseModel, Field, TypeAdapter, ValidationError

from .annotation import FrameAnnotation
from .camera import CameraIntrinsics
from .skeleton import Skeleton, get_skeleton

SESSION_FILE = "session.json"
JOURNAL_FILE = "journal.jsonl"
RESULTS_FILE = "results.npz"
CROPS_FILE = "crops.npy"
CROPS_META_FILE = "crops_meta.npz"
RESULT_KEYS = ("lifted_mm", "init_mm", "final_mm", "confidence")


class SessionError(RuntimeError):
    """A session folder is missing, corrupt or cannot be written. The message names the file."""


# ---------------------------------------------------------------------------------------------
# The persistent model


class DatasetSpec(BaseModel):
    path: str
    format: str
    intrinsics: CameraIntrinsics | None = None
    depth_scale_mm: float | None = None


class Settings(BaseModel):
    cube_mm: float = 220.0
    crop_size: int = 128
    descriptor: str = "downsampled"
    eps_mm: float = 15.0
    angle_limits: bool = True
    aligner: str = "dis"


class SelectionModel(BaseModel):
    strategy: str | None = None
    reference_frames: list[int] = Field(default_factory=list)
    parent: list[int] = Field(default_factory=list)
    threshold: float | None = None
    ref_fraction: float | None = None


class SessionModel(BaseModel):
    version: int = 1
    name: str
    dataset: DatasetSpec
    frames: int
    camera: CameraIntrinsics
    skeleton: str = "msra21"
    sequence_breaks: list[int] = Field(default_factory=list)
    settings: Settings = Field(default_factory=Settings)
    selection: SelectionModel = Field(default_factory=SelectionModel)
    #: frame index (as a string key) -> FrameAnnotation.to_json()
    annotations: dict[str, dict[str, Any]] = Field(default_factory=dict)
    bone_lengths_mm: list[float] | None = None
    bones_pinned: bool = False
    #: frame -> "accepted" | "flagged"
    review: dict[str, str] = Field(default_factory=dict)
    #: frames that became references through review corrections (annotation cost beyond the selection)
    corrections: list[int] = Field(default_factory=list)
    journal_seq: int = 0


# ---------------------------------------------------------------------------------------------
# Commands: every edit, with an inverse for undo


class _Command(BaseModel):
    frame: int

    def check(self, session: Session) -> None:
        if not 0 <= self.frame < session.model.frames:
            raise ValueError(
                f"frame {self.frame} out of range (session has {session.model.frames} frames)"
            )

    def inverse(self, session: Session) -> Command:  # pragma: no cover - abstract
        raise NotImplementedError

    def apply(self, session: Session) -> None:  # pragma: no cover - abstract
        raise NotImplementedError

    # shared helpers
    def _joint_check(self, session: Session, joint: int) -> None:
        if not 0 <= joint < session.skeleton.num_joints:
            raise ValueError(
                f"joint {joint} out of range (skeleton has {session.skeleton.num_joints} joints)"
            )


class SetFrameAnnotation(_Command):
    """Replace a frame's whole annotation (``None`` deletes it). Used by import and the simulated annotator."""

    kind: Literal["set_frame"] = "set_frame"
    annotation: dict[str, Any] | None

    def check(self, session: Session) -> None:
        super().check(session)
        if self.annotation is not None:
            FrameAnnotation.from_json(
                self.annotation, session.skeleton.num_joints, f"frame {self.frame}"
            )

    def inverse(self, session: Session) -> Command:
        return SetFrameAnnotation(
            frame=self.frame, annotation=session.model.annotations.get(str(self.frame))
        )

    def apply(self, session: Session) -> None:
        if self.annotation is None:
            session.model.annotations.pop(str(self.frame), None)
        else:
            session.model.annotations[str(self.frame)] = self.annotation


class _JointEdit(_Command):
    joint: int

    def check(self, session: Session) -> None:
        super().check(session)
        self._joint_check(session, self.joint)

    def _annotation(self, session: Session) -> FrameAnnotation:
        return session.annotation(self.frame) or FrameAnnotation.empty(session.skeleton.num_joints)

    def _store(self, session: Session, ann: FrameAnnotation) -> None:
        session.model.annotations[str(self.frame)] = ann.to_json()

    def inverse(self, session: Session) -> Command:
        # Restore only this joint, so undoing one annotator's edit never touches another's joints.
        ann = self._annotation(session)
        k = self.joint
        return SetJointState(
            frame=self.frame,
            joint=k,
            uv_px=None if np.isnan(ann.uv_px[k]).any() else tuple(ann.uv_px[k]),
            xyz_mm=None if np.isnan(ann.xyz_mm[k]).any() else tuple(ann.xyz_mm[k]),
            visible=bool(ann.visible[k]),
            order=int(ann.depth_order[k]),
        )


class SetJointState(_JointEdit):
    """Set everything about one joint at once (the inverse of every single-joint edit)."""

    kind: Literal["set_joint"] = "set_joint"
    uv_px: tuple[float, float] | None
    xyz_mm: tuple[float, float, float] | None
    visible: bool
    order: Literal[-1, 0, 1]

    def apply(self, session: Session) -> None:
        ann = self._annotation(session)
        k = self.joint
        ann.uv_px[k] = np.nan if self.uv_px is None else self.uv_px
        ann.xyz_mm[k] = np.nan if self.xyz_mm is None else self.xyz_mm
        ann.visible[k] = self.visible
        ann.depth_order[k] = self.order
        self._store(session, ann)


class SetJoint2D(_JointEdit):
    """Set (or clear, with ``None``) one joint's 2D position in image pixels."""

    kind: Literal["set_2d"] = "set_2d"
    uv_px: tuple[float, float] | None

    def check(self, session: Session) -> None:
        super().check(session)
        if self.uv_px is not None and not np.all(np.isfinite(self.uv_px)):
            raise ValueError("2D position must be finite")

    def apply(self, session: Session) -> None:
        ann = self._annotation(session)
        ann.uv_px[self.joint] = np.nan if self.uv_px is None else self.uv_px
        self._store(session, ann)


class SetJoint3D(_JointEdit):
    """Place (or clear) one joint directly in 3D (mm); its 2D position follows by projection."""

    kind: Literal["set_3d"] = "set_3d"
    xyz_mm: tuple[float, float, float] | None

    def check(self, session: Session) -> None:
        super().check(session)
        if self.xyz_mm is not None and (
            not np.all(np.isfinite(self.xyz_mm)) or self.xyz_mm[2] <= 0
        ):
            raise ValueError("3D position must be finite and in front of the camera")

    def apply(self, session: Session) -> None:
        ann = self._annotation(session)
        if self.xyz_mm is None:
            ann.xyz_mm[self.joint] = np.nan
        else:
            ann.xyz_mm[self.joint] = self.xyz_mm
            ann.uv_px[self.joint] = session.camera.project(np.asarray(self.xyz_mm))
        self._store(session, ann)


class SetVisibility(_JointEdit):
    kind: Literal["set_visible"] = "set_visible"
    visible: bool

    def apply(self, session: Session) -> None:
        ann = self._annotation(session)
        ann.visible[self.joint] = self.visible
        self._store(session, ann)


class SetDepthOrder(_JointEdit):
    """Depth of the joint relative to its parent: -1 closer, 0 unknown, +1 farther."""

    kind: Literal["set_depth_order"] = "set_depth_order"
    order: Literal[-1, 0, 1]

    def apply(self, session: Session) -> None:
        ann = self._annotation(session)
        ann.depth_order[self.joint] = self.order
        self._store(session, ann)


class SetReference(_Command):
    """Make a frame a reference (``is_reference=True``) or restore it to a propagated frame.

    ``parent`` is the parent to restore when un-making a reference; ``correction`` marks a frame
    that became a reference through review (counted as extra annotation cost).
    """

    kind: Literal["set_reference"] = "set_reference"
    is_reference: bool
    parent: int = -1
    correction: bool = False

    def inverse(self, session: Session) -> Command:
        sel = session.model.selection
        was_ref = self.frame in sel.reference_frames
        old_parent = sel.parent[self.frame] if sel.parent else -1
        return SetReference(
            frame=self.frame,
            is_reference=was_ref,
            parent=old_parent,
            correction=self.frame in session.model.corrections,
        )

    def apply(self, session: Session) -> None:
        sel = session.model.selection
        refs = set(sel.reference_frames)
        if not sel.parent:
            sel.parent = [-1] * session.model.frames
        if self.is_reference:
            refs.add(self.frame)
            sel.parent[self.frame] = -1
        else:
            refs.discard(self.frame)
            sel.parent[self.frame] = self.parent
        sel.reference_frames = sorted(refs)
        corrections = set(session.model.corrections)
        if self.is_reference and self.correction:
            corrections.add(self.frame)
        else:
            corrections.discard(self.frame)
        session.model.corrections = sorted(corrections)


class SetReview(_Command):
    kind: Literal["set_review"] = "set_review"
    status: Literal["accepted", "flagged"] | None

    def inverse(self, session: Session) -> Command:
        return SetReview(frame=self.frame, status=session.model.review.get(str(self.frame)))  # type: ignore[arg-type]

    def apply(self, session: Session) -> None:
        if self.status is None:
            session.model.review.pop(str(self.frame), None)
        else:
            session.model.review[str(self.frame)] = self.status


class Batch(BaseModel):
    """Several commands applied (and undone) as one edit."""

    kind: Literal["batch"] = "batch"
    commands: list[Annotated[Any, Field()]]

    @property
    def frame(self) -> int:
        return self.parsed()[0].frame if self.commands else -1

    def parsed(self) -> list[Command]:
        return [
            c if isinstance(c, BaseModel) else _COMMAND_ADAPTER.validate_python(c)
            for c in self.commands
        ]

    def check(self, session: Session) -> None:
        for c in self.parsed():
            c.check(session)

    def inverse(self, session: Session) -> Command:
        # Inverses must see the state each command replaces: compute them while applying to a copy.
        raise NotImplementedError  # handled specially in Session._inverse_of

    def apply(self, session: Session) -> None:
        for c in self.parsed():
            c.apply(session)


Command = Annotated[
    SetFrameAnnotation
    | SetJointState
    | SetJoint2D
    | SetJoint3D
    | SetVisibility
    | SetDepthOrder
    | SetReference
    | SetReview
    | Batch,
    Field(discriminator="kind"),
]
_COMMAND_ADAPTER: TypeAdapter[Any] = TypeAdapter(Command)


def parse_command(data: dict[str, Any]) -> Command:
    return _COMMAND_ADAPTER.validate_python(data)


# ---------------------------------------------------------------------------------------------
# Atomic file helpers


def atomic_write_bytes(path: Path, data: bytes) -> None:
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_save_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".npz")
    os.close(fd)
    try:
        np.savez(tmp, **arrays)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


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
    if os.sep in s or "/" in s or Path(s).exists():
        return Path(s)
    return safe_session_path(s, sessions_dir)


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


Listener = Callable[[JournalEntry], None]


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
    ) -> Session:
        folder = Path(folder)
        if (folder / SESSION_FILE).exists() and not overwrite:
            raise SessionError(f"{folder / SESSION_FILE}: a session already exists here")
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
        )
        for stale in (JOURNAL_FILE, RESULTS_FILE, CROPS_FILE, CROPS_META_FILE):
            (folder / stale).unlink(missing_ok=True)
        session = cls(folder, model)
        session.save()
        return session

    @classmethod
    def open(cls, folder: str | Path) -> Session:
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
        return session

    def _replay_journal(self) -> None:
        path = self.folder / JOURNAL_FILE
        if not path.exists():
            return
        lines = path.read_bytes().split(b"\n")
        entries: list[JournalEntry] = []
        for number, raw in enumerate(lines, start=1):
            if not raw.strip():
                continue
            try:
                entries.append(JournalEntry.model_validate_json(raw))
            except (ValidationError, ValueError) as exc:
                is_last = all(not rest.strip() for rest in lines[number:])
                if is_last:
                    # A torn final line is a write that never completed, so it was never acknowledged.
                    break
                raise SessionError(
                    f"{path}: line {number} is corrupt ({str(exc).splitlines()[0]})"
                ) from exc
        for entry in entries:
            if entry.seq > self.model.journal_seq:
                parse_command(entry.command).apply(self)
            self._track_undo(entry)
        if entries:
            self.model.journal_seq = max(self.model.journal_seq, entries[-1].seq)
        self._next_seq = self.model.journal_seq + 1

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
        p = self.model.selection.parent
        return np.asarray(p, dtype=np.int64) if p else np.full(self.num_frames, -2, dtype=np.int64)

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
        ann = self.annotation(frame)
        return ann is not None and bool(ann.annotated.all())

    def progress(self) -> tuple[int, int]:
        """(annotated references, references)."""
        refs = self.model.selection.reference_frames
        return sum(self.is_annotated(f) for f in refs), len(refs)

    def open_sequence(self):  # -> DepthSequence
        """The session's depth sequence (opened once, lazily)."""
        if self._sequence is None:
            from .datasets import open_sequence

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
        with self.lock:
            stack = self._undo.get(client)
            if not stack:
                return None
            target = stack[-1]
            return self._commit(parse_command(target.inverse), client, "undo", target.seq)

    def redo(self, client: str = "cli") -> JournalEntry | None:
        with self.lock:
            stack = self._redo.get(client)
            if not stack:
                return None
            target = stack[-1]
            return self._commit(parse_command(target.command), client, "redo", target.seq)

    def can_undo(self, client: str = "cli") -> bool:
        return bool(self._undo.get(client))

    def can_redo(self, client: str = "cli") -> bool:
        return bool(self._redo.get(client))

    def _inverse_of(self, command: Command) -> Command:
        if isinstance(command, Batch):
            # Each sub-command's inverse depends on the state left by the ones before it.
            saved = self.model.model_copy(deep=True)
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
            self.save()
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

    def _append_journal(self, entry: JournalEntry) -> None:
        if self._journal_file is None:
            self._journal_file = open(self.folder / JOURNAL_FILE, "ab")  # noqa: SIM115 - kept open
        line = entry.model_dump_json().encode() + b"\n"
        try:
            self._journal_file.write(line)
            self._journal_file.flush()
            os.fsync(self._journal_file.fileno())
        except OSError as exc:
            raise SessionError(
                f"{self.folder / JOURNAL_FILE}: cannot write the edit journal: {exc}"
            ) from exc

    # ------------------------------------------------------------------ bulk state (not journaled edits)
    def set_selection(self, selection: dict[str, Any]) -> None:
        """Store a new reference selection (from ``handanno select``); snapshot immediately."""
        with self.lock:
            parent = list(map(int, selection["parent"]))
            if len(parent) != self.num_frames:
                raise ValueError(
                    f"selection has {len(parent)} parents for {self.num_frames} frames"
                )
            self.model.selection = SelectionModel(
                strategy=selection.get("strategy"),
                reference_frames=sorted(map(int, selection["reference_frames"])),
                parent=parent,
                threshold=selection.get("threshold"),
                ref_fraction=selection.get("ref_fraction"),
            )
            self.model.corrections = []
            self.save()

    def set_bone_lengths(
        self, bone_lengths_mm: np.ndarray | None, pinned: bool | None = None
    ) -> None:
        with self.lock:
            self.model.bone_lengths_mm = (
                None if bone_lengths_mm is None else [float(x) for x in bone_lengths_mm]
            )
            if pinned is not None:
                self.model.bones_pinned = pinned
            self.save()

    def save(self) -> None:
        """Write the snapshot atomically (the journal stays the source of truth for later edits)."""
        with self.lock:
            atomic_write_bytes(
                self.folder / SESSION_FILE, self.model.model_dump_json(indent=1).encode()
            )
            self._edits_since_snapshot = 0

    def close(self) -> None:
        with self.lock:
            self.save()
            if self._journal_file is not None:
                self._journal_file.close()
                self._journal_file = None

    # ------------------------------------------------------------------ results
    def load_results(self) -> dict[str, np.ndarray]:
        """Results arrays; missing ones are NaN-filled: ``*_mm`` (N,J,3), ``confidence`` (N,J)."""
        n, j = self.num_frames, self.skeleton.num_joints
        out: dict[str, np.ndarray] = {
            "lifted_mm": np.full((n, j, 3), np.nan),
            "init_mm": np.full((n, j, 3), np.nan),
            "final_mm": np.full((n, j, 3), np.nan),
            "confidence": np.full((n, j), np.nan),
        }
        path = self.folder / RESULTS_FILE
        if path.exists():
            try:
                with np.load(path) as data:
                    for key in data.files:
                        out[key] = data[key]
            except (OSError, ValueError) as exc:
                raise SessionError(
                    f"{path}: corrupt results file ({exc}); rerun `handanno propagate`"
                ) from exc
        return out

    def save_results(self, **arrays: np.ndarray) -> None:
        """Update some result arrays (others kept) atomically."""
        with self.lock:
            current = self.load_results()
            current.update({k: np.asarray(v) for k, v in arrays.items()})
            atomic_save_npz(self.folder / RESULTS_FILE, current)

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
        return "\n".join(lines)

    def __enter__(self) -> Session:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
