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
from pathlib import Path
from typing import Any

import numpy as np

from .annotation import FrameAnnotation
from .session import (
    Batch,
    Session,
    SessionError,
    SetFrameAnnotation,
    SetReference,
    atomic_write_bytes,
)

EXPORT_FORMATS = ("json", "npz", "msra")
_VISIBILITY_MARGIN_MM = 10.0


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
    """Depth test per frame and joint: visible when nothing is much closer than the joint's surface."""
    sequence = session.open_sequence()
    camera = sequence.camera
    offsets = np.asarray(session.skeleton.surface_offsets_mm)
    visible = np.zeros(joints_mm.shape[:2], dtype=bool)
    for i in np.flatnonzero(np.all(np.isfinite(joints_mm), axis=(1, 2))):
        try:
            depth = sequence.depth(int(i))
        except ValueError:
            continue
        uv = np.rint(camera.project(joints_mm[i])).astype(np.int64)
        inside = (
            (uv[:, 0] >= 0)
            & (uv[:, 0] < camera.width)
            & (uv[:, 1] >= 0)
            & (uv[:, 1] < camera.height)
        )
        d = np.zeros(len(uv))
        d[inside] = depth[uv[inside, 1], uv[inside, 0]]
        visible[i] = inside & (d > 0) & (d >= joints_mm[i, :, 2] - offsets - _VISIBILITY_MARGIN_MM)
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
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(path, export_bytes(session, fmt))
    return path


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


def import_json(session: Session, path: str | Path, client: str = "import") -> int:
    """Import a handanno JSON export: reference annotations (one undoable edit) and the 3D joints.

    Returns the number of frames with joints imported. Raises SessionError naming the file on bad input.
    """
    path = Path(path)
    try:
        doc = json.loads(path.read_bytes())
    except (OSError, json.JSONDecodeError) as exc:
        raise SessionError(f"{path}: not a readable JSON export ({exc})") from exc
    if doc.get("format") != "handanno-export":
        raise SessionError(f"{path}: not a handanno export (missing 'format': 'handanno-export')")
    frames = doc.get("frames", [])
    if len(frames) != session.num_frames or doc.get("skeleton") != session.model.skeleton:
        raise SessionError(
            f"{path}: export has {len(frames)} frames / skeleton {doc.get('skeleton')}, session has "
            f"{session.num_frames} / {session.model.skeleton}"
        )
    j = session.skeleton.num_joints
    joints = np.full((session.num_frames, j, 3), np.nan)
    confidence = np.full((session.num_frames, j), np.nan)
    commands = []
    for entry in frames:
        i = int(entry["frame"])
        if entry.get("joints_mm") is not None:
            joints[i] = np.asarray(entry["joints_mm"], dtype=np.float64).reshape(j, 3)
        confidence[i] = np.asarray(entry["confidence"], dtype=np.float64)
        if entry.get("annotation") is not None:
            ann = FrameAnnotation.from_json(entry["annotation"], j, f"{path} frame {i}")
            commands.append(SetFrameAnnotation(frame=i, annotation=ann.to_json()).model_dump())
        if entry.get("is_reference") and i not in set(session.model.selection.reference_frames):
            commands.append(SetReference(frame=i, is_reference=True).model_dump())
    if commands:
        session.execute(Batch(commands=commands), client=client)
    session.save_results(final_mm=joints, confidence=confidence)
    return int(np.all(np.isfinite(joints), axis=(1, 2)).sum())
