"""Export a session's result as JSON, NPZ or the MSRA ``joint.txt`` layout, and import the JSON back.

Per frame: 3D joints in mm (camera frame), 2D joints in px, visibility, confidence in [0, 1] (0 for
a joint never annotated nor estimated: no 3D position) and
whether the frame is a reference. The joints exported are the best available stage per frame:
refined, else propagated, else lifted. Visibility of a reference is its annotation; for other frames
it is a depth test of the exported joints against the frame's own depth map.
"""

from __future__ import annotations

import io
import json
import os
import stat
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, ValidationError, ValidationInfo, field_validator

from .annotation import FrameAnnotation
from .sampling import visible_by_depth
from .session import (
    Batch,
    Session,
    SessionError,
    SetFrameAnnotation,
    SetReference,
    atomic_write_bytes,
)

EXPORT_FORMATS = ("json", "npz", "msra")


def best_joints(results: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """``(N,J,3)`` best available joints and ``(N,)`` stage per frame (0 none, 1 lifted, 2 init, 3 final)."""
    joints = np.full_like(results["final_mm"], np.nan)
    stage = np.zeros(joints.shape[0], dtype=np.int8)
    for level, key in ((1, "lifted_mm"), (2, "init_mm"), (3, "final_mm")):
        ok = np.all(np.isfinite(results[key]), axis=(1, 2))
        joints[ok] = results[key][ok]
        stage[ok] = level
    return joints, stage


def _visibility(session: Session, joints_mm: np.ndarray) -> np.ndarray:
    """``(N, J)`` visibility of the exported joints by :func:`sampling.visible_by_depth` (False
    where a frame has no estimate or its depth cannot be read)."""
    sequence = session.open_sequence()
    offsets = np.asarray(session.skeleton.surface_offsets_mm)
    visible = np.zeros(joints_mm.shape[:2], dtype=bool)
    for i in np.flatnonzero(np.all(np.isfinite(joints_mm), axis=(1, 2))):
        try:
            depth = sequence.depth(int(i))
        except ValueError:
            continue
        visible[i] = visible_by_depth(joints_mm[i], depth, sequence.camera, offsets)
    return visible


def collect(session: Session) -> dict[str, Any]:
    """Everything an export needs, as arrays: joints_mm, uv_px, visible, confidence, is_reference."""
    results = session.load_results()
    joints, stage = best_joints(results)
    visible = _visibility(session, joints)
    is_reference = np.zeros(session.num_frames, dtype=bool)
    is_reference[session.reference_frames] = True
    for f, ann in session.annotations(session.reference_frames).items():
        visible[f] = ann.visible
    confidence = np.where(np.isfinite(results["confidence"]), results["confidence"], 0.0)
    confidence[is_reference] = np.where(
        np.isfinite(results["confidence"][is_reference]), confidence[is_reference], 1.0
    )
    # a joint that was never annotated or estimated (no 3D position) has confidence 0
    confidence = np.where(np.all(np.isfinite(joints), axis=-1), confidence, 0.0)
    return {
        "joints_mm": joints,
        "uv_px": session.camera.project(joints),
        "visible": visible,
        "confidence": confidence,
        "is_reference": is_reference,
        "stage": stage,
    }


def export_session(session: Session, fmt: str, path: str | Path) -> Path:
    """Write the export in ``fmt`` (json | npz | msra) to ``path``; returns the path written."""
    if fmt not in EXPORT_FORMATS:
        raise ValueError(
            f"unknown export format {fmt!r}; choose one of {', '.join(EXPORT_FORMATS)}"
        )
    path = Path(path)
    if path.is_symlink() or (path.exists() and not path.is_file()):
        kind = "symbolic link" if path.is_symlink() else _file_kind(path)
        raise SessionError(f"{path}: is a {kind}; export writes regular files only (not replaced)")
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(path, export_bytes(session, fmt))
    return path


def _file_kind(path: Path) -> str:
    mode = os.lstat(path).st_mode
    for test, name in (
        (stat.S_ISDIR, "folder"),
        (stat.S_ISFIFO, "FIFO"),
        (stat.S_ISSOCK, "socket"),
        (stat.S_ISCHR, "character device"),
        (stat.S_ISBLK, "block device"),
    ):
        if test(mode):
            return name
    return "special file"


def export_bytes(session: Session, fmt: str) -> bytes:
    data = collect(session)
    if fmt == "npz":
        buf = io.BytesIO()
        np.savez_compressed(buf, **data, joint_names=np.asarray(session.skeleton.joint_names))
        return buf.getvalue()
    if fmt == "msra":
        joints = np.nan_to_num(data["joints_mm"])
        # MSRA convention: y up and z negative (our frame is OpenCV: y down, z forward).
        msra = joints * np.array([1.0, -1.0, -1.0])
        lines = [str(len(msra))] + [" ".join(f"{v:.4f}" for v in row.ravel()) for row in msra]
        return ("\n".join(lines) + "\n").encode()
    annotations = session.annotations(session.reference_frames)
    frames = []
    for i in range(session.num_frames):
        finite = bool(np.all(np.isfinite(data["joints_mm"][i])))
        entry: dict[str, Any] = {
            "frame": i,
            "is_reference": bool(data["is_reference"][i]),
            "joints_mm": np.round(data["joints_mm"][i], 3).tolist() if finite else None,
            "uv_px": np.round(data["uv_px"][i], 3).tolist() if finite else None,
            "visible": data["visible"][i].tolist(),
            "confidence": np.round(data["confidence"][i], 4).tolist(),
        }
        if i in annotations:
            entry["annotation"] = annotations[i].to_json()
        frames.append(entry)
    doc = {
        "format": "handanno-export",
        "version": 1,
        "session": session.model.name,
        "dataset": session.model.dataset.model_dump(),
        "camera": session.camera.model_dump(),
        "skeleton": session.model.skeleton,
        "joint_names": list(session.skeleton.joint_names),
        "units": {"joints_mm": "mm, camera frame x right, y down, z forward", "uv_px": "pixels"},
        "references": int(data["is_reference"].sum()),
        "corrections": session.model.corrections,
        "frames": frames,
    }
    return json.dumps(doc).encode()


#: Plausible joint positions for import (mm, camera frame): in front of the camera between 5 cm and
#: 5 m, at most 5 m off its axis. Depth sensors measure hands well inside this box.
IMPORT_Z_RANGE_MM = (50.0, 5000.0)
IMPORT_XY_MAX_MM = 5000.0


def _one_per_joint(v: list | None, info: ValidationInfo, what: str) -> bool:
    """False for an absent list; ``ValueError`` unless it has one ``what`` per skeleton joint."""
    if v is None:
        return False
    j = info.context["joints"]
    if len(v) != j:
        raise ValueError(f"{len(v)} {what}, the skeleton has {j}")
    return True


class _ImportFrame(BaseModel):
    """One frame of a handanno JSON export, checked against the session (``context``)."""

    model_config = ConfigDict(extra="ignore", allow_inf_nan=False)

    frame: int
    is_reference: bool = False
    joints_mm: list[tuple[float, float, float]] | None = None
    confidence: list[float | None] | None = None
    annotation: dict[str, Any] | None = None

    @field_validator("frame")
    @classmethod
    def _frame_in_range(cls, v: int, info: ValidationInfo) -> int:
        n = info.context["frames"]
        if not 0 <= v < n:
            raise ValueError(f"frame {v} out of range (session has {n} frames)")
        return v

    @field_validator("joints_mm")
    @classmethod
    def _plausible_joints(cls, v, info: ValidationInfo):
        if not _one_per_joint(v, info, "joints"):
            return v
        xyz = np.asarray(v, dtype=np.float64)
        lo, hi = IMPORT_Z_RANGE_MM
        bad = (xyz[:, 2] < lo) | (xyz[:, 2] > hi) | (np.abs(xyz[:, :2]) > IMPORT_XY_MAX_MM).any(1)
        if bad.any():
            k = int(np.flatnonzero(bad)[0])
            raise ValueError(
                f"joint {k} at {tuple(round(float(c), 1) for c in xyz[k])} mm is not a plausible "
                f"hand position (z in [{lo:g}, {hi:g}] mm, |x|, |y| <= {IMPORT_XY_MAX_MM:g} mm)"
            )
        return v

    @field_validator("confidence")
    @classmethod
    def _confidence_in_unit_range(cls, v, info: ValidationInfo):
        if not _one_per_joint(v, info, "confidences"):
            return v
        if any(c is not None and not 0.0 <= c <= 1.0 for c in v):
            raise ValueError("confidences must lie in [0, 1]")
        return v


class _ImportDoc(BaseModel):
    model_config = ConfigDict(extra="ignore")

    format: Literal["handanno-export"]
    skeleton: str
    frames: list[_ImportFrame]


def _import_error(path: Path, exc: ValidationError) -> SessionError:
    err = exc.errors()[0]
    loc = ".".join(str(x) for x in err.get("loc", ()))
    msg = str(err["msg"]).removeprefix("Value error, ")
    return SessionError(f"{path}: {loc}: {msg}" if loc else f"{path}: {msg}")


def _parse_import(session: Session, path: Path) -> _ImportDoc:
    """The checked export document (see :func:`import_json`); ``SessionError`` naming the problem."""
    try:
        doc = json.loads(path.read_bytes())
    except (OSError, ValueError, RecursionError) as exc:
        raise SessionError(f"{path}: not a readable JSON export ({exc})") from exc
    if not isinstance(doc, dict) or doc.get("format") != "handanno-export":
        raise SessionError(f"{path}: not a handanno export (missing 'format': 'handanno-export')")
    n, j = session.num_frames, session.skeleton.num_joints
    try:
        parsed = _ImportDoc.model_validate(doc, context={"frames": n, "joints": j})
    except ValidationError as exc:
        raise _import_error(path, exc) from None
    if len(parsed.frames) != n or parsed.skeleton != session.model.skeleton:
        raise SessionError(
            f"{path}: export has {len(parsed.frames)} frames / skeleton {parsed.skeleton}, "
            f"session has {n} / {session.model.skeleton}"
        )
    seen = [f.frame for f in parsed.frames]
    if len(set(seen)) != n:
        dup = next(f for f in seen if seen.count(f) > 1)
        raise SessionError(f"{path}: frame {dup} appears more than once")
    if not any(f.joints_mm is not None or f.annotation is not None for f in parsed.frames):
        raise SessionError(f"{path}: no frame has joints or an annotation; nothing to import")
    return parsed


def _imported_annotation(data: dict[str, Any], j: int, where: str) -> FrameAnnotation:
    """A reference annotation from an export entry; ``SessionError`` naming ``where`` if bad."""
    try:
        ann = FrameAnnotation.from_json(data, j, where)
    except ValueError as exc:
        raise SessionError(" ".join(str(exc).split())) from None
    placed = np.isfinite(ann.xyz_mm).all(axis=1)
    if np.isinf(ann.uv_px).any() or np.isinf(ann.xyz_mm).any():
        raise SessionError(f"{where}: infinite positions")
    if np.any(ann.xyz_mm[placed, 2] <= 0):
        raise SessionError(f"{where}: a joint placed behind the camera (z <= 0)")
    return ann


def import_json(session: Session, path: str | Path, client: str = "import") -> int:
    """Import a handanno JSON export: reference annotations (one undoable edit) and the 3D joints.

    The whole file is checked first (:class:`_ImportDoc`: frame indices in range and unique, the
    session's frame count and skeleton, finite joints at plausible positions, confidences in
    [0, 1], well-formed annotations); on any problem a :class:`SessionError` names the file, the
    entry and the reason, and the session is left unchanged. Frames without ``joints_mm`` keep the
    session's current result. Returns the number of frames with joints imported.
    """
    path = Path(path)
    parsed = _parse_import(session, path)
    j = session.skeleton.num_joints
    results = session.load_results()
    joints, confidence = results["final_mm"], results["confidence"]
    commands = []
    references = set(session.model.selection.reference_frames)
    for entry in parsed.frames:
        i = entry.frame
        if entry.joints_mm is not None:
            joints[i] = np.asarray(entry.joints_mm, dtype=np.float64)
            if entry.confidence is not None:
                confidence[i] = np.array(entry.confidence, dtype=np.float64)
        if entry.annotation is not None:
            ann = _imported_annotation(entry.annotation, j, f"{path}: frames.{i}.annotation")
            commands.append(SetFrameAnnotation(frame=i, annotation=ann.to_json()))
        if entry.is_reference and i not in references:
            commands.append(SetReference(frame=i, is_reference=True))
    batch = Batch(commands=[c.model_dump() for c in commands])
    try:
        batch.check(session)
    except ValueError as exc:
        raise SessionError(f"{path}: {' '.join(str(exc).split())}") from None
    with session.lock:
        entry = session.execute(batch, client=client) if commands else None
        try:
            session.save_results(final_mm=joints, confidence=confidence)
        except BaseException:
            if entry is not None:  # all or nothing: take the annotations back out
                session.undo(client)
            raise
    return sum(f.joints_mm is not None for f in parsed.frames)
