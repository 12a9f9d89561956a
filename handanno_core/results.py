"""``results.npz``: the session's derived joints, one format, read and checked in one place.

Arrays (float64): ``lifted_mm``, ``init_mm``, ``final_mm`` ``(N, J, 3)`` in mm (camera frame),
``confidence`` ``(N, J)`` in [0, 1] and ``model_fit`` ``(N, T)`` (:data:`MODEL_FIT_TERMS`); NaN
where a stage has no value for a frame. ``source`` ``(N,)`` int64: the frame each propagated
result was propagated from, the parent of the candidate forest propagation kept for it
(:func:`handanno_core.propagate.propagate`: the selection's forest or a temporal chain), and
:data:`NO_SOURCE` (-1) for references and frames without a propagated result. It names a frame,
not that frame's stored pose: the pose flowed was the source's result along the same candidate
chain, which the source itself may not have kept, so ``source`` is not a forest (frame 5 from 6
and 6 from 5 happens: 62 of the 2,247 frames of the seed-0 tune part, forest 5 %, are in such
pairs). Do not walk it to find a reference; planning uses the selection's forest. Files
written before ``source`` existed open with it filled from the selection's parent forest
(:func:`fallback_source`): exact for a run along that forest alone, a guess where propagation
also had the temporal chains. The file is always written whole
(:func:`handanno_core.fileio.atomic_save_npz`) by
:meth:`handanno_core.session.Session.save_results`; partial progress lives elsewhere.
"""

from __future__ import annotations

from enum import IntEnum
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from .session import Session

RESULTS_FILE = "results.npz"
RESULT_KEYS = ("lifted_mm", "init_mm", "final_mm", "confidence", "model_fit", "source")
#: ``source`` of a frame that was not propagated (a reference, skipped, not computed yet)
NO_SOURCE = -1
#: the columns of ``model_fit`` (N, T): the hand-model fit's own evidence per propagated frame
#: (``handanno_core.propagate._model_fits``; NaN without the model): ``level`` the best fit's
#: data + free-space energy over the references' level (the propagation guard's ratio),
#: ``data_mm`` mean |point-to-surface| mm of the observed points at the kept pose, ``free`` the
#: fraction of the capsules' free-space samples violated at the kept pose, ``rejected`` 1 where
#: the guard kept the flowed pose (the fit did not explain the depth), else 0.
MODEL_FIT_TERMS = ("level", "data_mm", "free", "rejected")


class Stage(IntEnum):
    """The best stage a frame's joints come from (``handanno_core.export.best_joints``)."""

    NONE = 0
    LIFTED = 1  # lifted_mm: a reference lifted from its 2D/3D annotation
    PROPAGATED = 2  # init_mm: propagated from the frame ``source`` names
    REFINED = 3  # final_mm: after global refinement


class ResultsError(ValueError):
    """A results file is unreadable or does not fit its session; the message names the file."""


def result_shape(key: str, frames: int, joints: int) -> tuple[int, ...]:
    """Shape of result array ``key`` for a session of ``frames`` frames and ``joints`` joints."""
    if key == "source":
        return (frames,)
    if key == "model_fit":
        return (frames, len(MODEL_FIT_TERMS))
    return (frames, joints) if key == "confidence" else (frames, joints, 3)


def result_dtype(key: str) -> type:
    """dtype of result array ``key``: int64 for ``source`` (frame indices), else float64."""
    return np.int64 if key == "source" else np.float64


def fallback_source(init_mm: np.ndarray, parent: np.ndarray | None) -> np.ndarray:
    """``(N,)`` int64 ``source`` for a results file written without one: the selection's
    ``parent`` (N,) where the frame has propagated joints ``init_mm`` (N, J, 3) and a parent,
    else :data:`NO_SOURCE` (everywhere without ``parent``)."""
    n = len(init_mm)
    if parent is None or len(parent) != n:
        return np.full(n, NO_SOURCE, dtype=np.int64)
    parent = np.asarray(parent, dtype=np.int64)
    propagated = np.all(np.isfinite(init_mm), axis=(1, 2)) & (parent >= 0)
    return np.where(propagated, parent, NO_SOURCE)


def read_results(
    path: str | Path, frames: int, joints: int, parent: np.ndarray | None = None
) -> dict[str, np.ndarray]:
    """Every result array; missing arrays (or a missing file) NaN-filled, a missing ``source``
    :func:`fallback_source` of the selection's ``parent`` (N,) (:data:`NO_SOURCE` without it).

    Raises :class:`ResultsError` naming ``path`` for a truncated, empty or non-zip file, or arrays
    of the wrong shape (another session's results); unknown arrays are ignored.
    """
    path = Path(path)
    out = {
        k: np.full(
            result_shape(k, frames, joints),
            NO_SOURCE if k == "source" else np.nan,
            dtype=result_dtype(k),
        )
        for k in RESULT_KEYS
    }
    if not path.exists():
        return out
    hint = f"move it away and rerun `handanno lift` and `handanno propagate` ({path})"
    try:
        with np.load(path, allow_pickle=False) as data:
            for key in data.files:
                if key in out:
                    out[key] = np.asarray(data[key], dtype=result_dtype(key))
            stored_source = "source" in data.files
    except Exception as exc:  # BadZipFile, EOFError, ValueError, OSError, zlib.error
        reason = str(exc).splitlines()[0] if str(exc) else ""
        raise ResultsError(
            f"{path}: corrupt results file ({type(exc).__name__}: {reason}); {hint}"
        ) from exc
    for key, value in out.items():
        expected = result_shape(key, frames, joints)
        if value.shape != expected:
            raise ResultsError(
                f"{path}: {key} has shape {value.shape}, expected {expected} for this session; {hint}"
            )
    if not stored_source:
        out["source"] = fallback_source(out["init_mm"], parent)
    elif np.any((out["source"] < NO_SOURCE) | (out["source"] >= frames)):
        raise ResultsError(f"{path}: source holds frames outside 0-{frames - 1}; {hint}")
    return out


def update_lifted(
    session: Session, lifted: dict[int, tuple[np.ndarray, np.ndarray | None]]
) -> None:
    """Write ``{frame: (joints (J, 3) mm, confidence (J,) or None)}`` into ``lifted_mm`` /
    ``confidence`` of ``session``'s results: one read-modify-write under the session lock, so a
    concurrent save (the review runner's, the lift worker's) is never overwritten with stale
    arrays."""
    if not lifted:
        return
    with session.lock:
        current = session.load_results()
        lifted_mm, conf = current["lifted_mm"], current["confidence"]
        for frame, (joints, confidence) in lifted.items():
            lifted_mm[frame] = joints
            conf[frame] = 1.0 if confidence is None else confidence
        session.save_results(lifted_mm=lifted_mm, confidence=conf)


def describe_sources(source: np.ndarray, parent: np.ndarray) -> str:
    """One line on where the propagated results came from: how many frames have a ``source``
    (N,) (:data:`NO_SOURCE` elsewhere) and how many of them kept another chain than the
    selection's ``parent`` (N,) forest, with a few examples."""
    source = np.asarray(source, dtype=np.int64)
    parent = np.asarray(parent, dtype=np.int64)
    propagated = np.flatnonzero(source >= 0)
    other = propagated[source[propagated] != parent[propagated]]
    line = f"propagated results: {len(propagated)} frame(s)"
    if len(propagated):
        line += f", {len(other)} kept another chain than the selection's parent"
        if len(other):
            examples = ", ".join(f"{int(f)} from {int(source[f])}" for f in other[:5])
            line += f" ({examples}{', ...' if len(other) > 5 else ''})"
    return line


def describe_frame(frame: int, source: np.ndarray, parent: np.ndarray, stage: int) -> str:
    """One line on ``frame``: a reference; or, with its best :class:`Stage` ``stage``, either not
    propagated or the frame its result was propagated from (``source``), naming the selection's
    ``parent`` when the result kept another chain."""
    p, s, what = int(parent[frame]), int(source[frame]), Stage(stage).name.lower()
    if p == -1:
        return f"frame {frame}: reference"
    if s < 0:
        return f"frame {frame} ({what}): no propagated result"
    via = "" if s == p else f", not the selection's parent {p}"
    return f"frame {frame} ({what}): propagated from frame {s}{via}"
