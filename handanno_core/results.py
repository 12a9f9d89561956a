"""``results.npz``: the session's derived joints, one format, read and checked in one place.

Arrays (float64): ``lifted_mm``, ``init_mm``, ``final_mm`` ``(N, J, 3)`` in mm (camera frame),
``confidence`` ``(N, J)`` in [0, 1] and ``model_fit`` ``(N, T)`` (:data:`MODEL_FIT_TERMS`); NaN
where a stage has no value for a frame. The file is always written whole
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
RESULT_KEYS = ("lifted_mm", "init_mm", "final_mm", "confidence", "model_fit")
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
    PROPAGATED = 2  # init_mm: propagated from its parent in the reference forest
    REFINED = 3  # final_mm: after global refinement


class ResultsError(ValueError):
    """A results file is unreadable or does not fit its session; the message names the file."""


def result_shape(key: str, frames: int, joints: int) -> tuple[int, ...]:
    """Shape of result array ``key`` for a session of ``frames`` frames and ``joints`` joints."""
    if key == "model_fit":
        return (frames, len(MODEL_FIT_TERMS))
    return (frames, joints) if key == "confidence" else (frames, joints, 3)


def read_results(path: str | Path, frames: int, joints: int) -> dict[str, np.ndarray]:
    """Every result array; missing arrays (or a missing file) NaN-filled.

    Raises :class:`ResultsError` naming ``path`` for a truncated, empty or non-zip file, or arrays
    of the wrong shape (another session's results); unknown arrays are ignored.
    """
    path = Path(path)
    out = {k: np.full(result_shape(k, frames, joints), np.nan) for k in RESULT_KEYS}
    if not path.exists():
        return out
    hint = f"move it away and rerun `handanno lift` and `handanno propagate` ({path})"
    try:
        with np.load(path, allow_pickle=False) as data:
            for key in data.files:
                if key in out:
                    out[key] = np.asarray(data[key], dtype=np.float64)
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
