"""Review logic without viser: per-frame review scores, "next worst frame", review corrections, and
the background job that propagates and refines while the app streams its results.

* :func:`frame_scores` - a pure-numpy per-frame score in [0, 1] (1 = trustworthy) from the
  propagation confidence (which already contains the forward-backward flow consistency), bone-length
  anomalies, depth residuals, temporal jumps and an optional flow-inconsistency term.
* :func:`worst_order` / :func:`next_worst` - walk frames by increasing score.
* :func:`correction_command` - the session command of a review edit: on a propagated frame it is a
  :class:`~handanno_core.session.Batch` that makes the frame a reference (``correction=True``),
  seeds its annotation from the shown skeleton and applies the joint edit, all as one undo step.
* :class:`LiveResults` - the joints shown by the review view, updated frame by frame while a job
  runs (``on_result``), thread-safe.
* :class:`ReviewRunner` - one background thread running "propagate & refine" jobs: a full run, or
  after review corrections only the corrected frames' descendants in the parent forest; and "lift
  all" (:func:`handanno_core.pipeline.lift`: every annotated reference, bone lengths estimated),
  which a full run does first when the session has no bone lengths or an annotated reference has
  no lifted pose (a session annotated only in the browser). Cancelling leaves ``results.npz``
  either as it was (or as the finished lift left it) or completely new (never half-written) and
  never touches the journal.
"""

from __future__ import annotations

import threading
import time
import traceback
import warnings
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from handanno_core.annotation import FrameAnnotation
from handanno_core.camera import CameraIntrinsics
from handanno_core.session import (
    Batch,
    Command,
    Session,
    SessionError,
    SetFrameAnnotation,
    SetJoint3D,
    SetReference,
    atomic_save_npz,
)

#: scale of each score term: a term equal to its scale halves the score (``1 / (1 + (x/s)^2)``).
SCORE_SCALES = {"bone": 0.10, "depth_mm": 15.0, "jump_mm": 30.0, "flow_px": 3.0}
#: penalty (mm) of a joint projecting onto background / outside the hand cube.
OFF_HAND_MM = 40.0
PARTIAL_FILE = "propagation_partial.npz"


# =============================================================================================
# scores (pure numpy)


def bone_anomaly(
    joints_mm: np.ndarray, bones: np.ndarray, bone_lengths_mm: np.ndarray
) -> np.ndarray:
    """``(N,)`` largest relative bone-length deviation per frame (0 = exact; NaN if no joints).

    ``joints_mm`` (N, J, 3) mm, ``bones`` (B, 2) (parent, child), ``bone_lengths_mm`` (B,) mm.
    """
    j = np.asarray(joints_mm, dtype=np.float64)
    b = np.asarray(bones, dtype=np.int64)
    lengths = np.linalg.norm(j[:, b[:, 1]] - j[:, b[:, 0]], axis=-1)  # (N, B)
    ref = np.asarray(bone_lengths_mm, dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        dev = np.abs(lengths - ref) / np.maximum(ref, 1e-6)
        out = np.max(dev, axis=1)
    out[~np.all(np.isfinite(dev), axis=1)] = np.nan
    return out


def temporal_jump(joints_mm: np.ndarray, sequence_breaks: Iterable[int] = ()) -> np.ndarray:
    """``(N,)`` mm: for each frame the largest joint displacement to its previous and to its next
    frame, and of those two the *smaller* one (a single wrong frame jumps away from both of its
    neighbours; a frame next to it only from one). Jumps across sequence breaks are ignored; NaN
    where no neighbour has joints."""
    j = np.asarray(joints_mm, dtype=np.float64)
    n = len(j)
    step = np.full(n + 1, np.nan)  # step[t] = jump between frame t-1 and t
    if n > 1:
        d = np.max(np.linalg.norm(j[1:] - j[:-1], axis=-1), axis=1)
        step[1:n] = d
    for b in sequence_breaks:
        if 0 < int(b) < n:
            step[int(b)] = np.nan
    prev, nxt = step[:n], step[1 : n + 1]
    with np.errstate(invalid="ignore"):
        out = np.fmin(prev, nxt)
    out[~np.all(np.isfinite(j), axis=(1, 2))] = np.nan
    return out


def depth_residuals(
    joints_mm: np.ndarray,
    crops: np.ndarray,
    boxes: np.ndarray,
    centres_mm: np.ndarray,
    camera: CameraIntrinsics,
    *,
    cube_mm: float = 220.0,
    surface_offsets_mm: np.ndarray | None = None,
) -> np.ndarray:
    """``(N, J)`` mm: how far each joint sits *in front of* the observed surface (a joint centre
    lies on or behind it), read from the normalized crops (no depth file is opened); a joint that
    projects onto background or outside the crop costs :data:`OFF_HAND_MM`. NaN without joints.

    ``crops`` (N, S, S) normalized depth ``(d - z_c) / (cube_mm / 2)``, +1 = background;
    ``boxes`` (N, 4) ``[u_left, v_top, sx, sy]``; ``centres_mm`` (N, 3).
    """
    from handanno_core.crops import image_to_crop

    j = np.asarray(joints_mm, dtype=np.float64)
    n, nj = j.shape[:2]
    out = np.full((n, nj), np.nan)
    ok = np.all(np.isfinite(j), axis=(1, 2))
    if not ok.any():
        return out
    frames = np.flatnonzero(ok)
    jj = j[frames]
    uv = camera.project(jj)  # (M, J, 2)
    xy = image_to_crop(uv, np.asarray(boxes, dtype=np.float64)[frames][:, None, :])
    size = crops.shape[1]
    xy = np.where(np.isfinite(xy), xy, -1.0)  # joints at z <= 0 project nowhere: off the crop
    xi = np.rint(xy[..., 0]).astype(np.int64)
    yi = np.rint(xy[..., 1]).astype(np.int64)
    inside = (xi >= 0) & (xi < size) & (yi >= 0) & (yi < size)
    fi = np.broadcast_to(frames[:, None], xi.shape)
    vals = np.ones(xi.shape, dtype=np.float64)
    vals[inside] = np.asarray(crops[fi[inside], yi[inside], xi[inside]], dtype=np.float64)
    background = ~inside | (vals >= 0.999)
    observed = np.asarray(centres_mm, dtype=np.float64)[frames, 2][:, None] + vals * (cube_mm / 2.0)
    offsets = (
        0.0
        if surface_offsets_mm is None
        else np.asarray(surface_offsets_mm, dtype=np.float64)[None, :]
    )
    # A visible joint centre sits ~offset behind the surface: in front of (observed + offset) is wrong.
    res = np.maximum(observed + offsets - jj[..., 2], 0.0)
    res = np.where(background, OFF_HAND_MM, np.minimum(res, OFF_HAND_MM))
    out[frames] = res
    return out


@dataclass
class FrameScores:
    """``score`` (N,) in [0, 1], 1 = trustworthy, NaN = nothing to review (no joints); ``terms``:
    each ingredient (N,) in its own unit (``confidence`` 0..1, ``bone`` relative, ``depth_mm``,
    ``jump_mm``, ``flow_px``)."""

    score: np.ndarray
    terms: dict[str, np.ndarray] = field(default_factory=dict)


def _goodness(x: np.ndarray, scale: float) -> np.ndarray:
    """1 / (1 + (x / scale)^2), with NaN (term unavailable) -> 1."""
    g = 1.0 / (1.0 + (np.asarray(x, dtype=np.float64) / scale) ** 2)
    return np.where(np.isfinite(g), g, 1.0)


def frame_scores(
    confidence: np.ndarray,
    joints_mm: np.ndarray,
    bones: np.ndarray,
    bone_lengths_mm: np.ndarray | None,
    *,
    depth_residual_mm: np.ndarray | None = None,
    flow_error_px: np.ndarray | None = None,
    sequence_breaks: Iterable[int] = (),
    is_reference: np.ndarray | None = None,
    scales: dict[str, float] | None = None,
) -> FrameScores:
    """Combine the review evidence into one score per frame (see :class:`FrameScores`).

    ``confidence`` (N, J) in [0, 1] (propagation confidence, NaN = unknown -> 0.5);
    ``joints_mm`` (N, J, 3) the skeletons shown; ``bone_lengths_mm`` (B,) or None (no bone term);
    ``depth_residual_mm`` (N, J) from :func:`depth_residuals`; ``flow_error_px`` (N,) or (N, J)
    flow inconsistency (optional; the propagation confidence already includes its forward-backward
    consistency). Reference frames score 1. The score is the product of the per-frame confidence
    (mean and minimum over joints, averaged) and ``1 / (1 + (x / scale)^2)`` for each other term.
    """
    s = dict(SCORE_SCALES, **(scales or {}))
    joints = np.asarray(joints_mm, dtype=np.float64)
    n = len(joints)
    has = np.all(np.isfinite(joints), axis=(1, 2))
    conf = np.asarray(confidence, dtype=np.float64)
    conf = np.where(np.isfinite(conf), np.clip(conf, 0.0, 1.0), 0.5)
    c = 0.5 * (conf.mean(axis=1) + conf.min(axis=1)) if conf.size else np.ones(n)
    terms: dict[str, np.ndarray] = {"confidence": c}
    score = c.copy()
    if bone_lengths_mm is not None:
        terms["bone"] = bone_anomaly(joints, bones, bone_lengths_mm)
        score *= _goodness(terms["bone"], s["bone"])
    if depth_residual_mm is not None:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # frames without joints: NaN
            terms["depth_mm"] = np.nanmean(np.asarray(depth_residual_mm, dtype=np.float64), axis=1)
        score *= _goodness(terms["depth_mm"], s["depth_mm"])
    terms["jump_mm"] = temporal_jump(joints, sequence_breaks)
    score *= _goodness(terms["jump_mm"], s["jump_mm"])
    if flow_error_px is not None:
        f = np.asarray(flow_error_px, dtype=np.float64)
        if f.ndim == 2:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                f = np.nanmean(f, axis=1)
        terms["flow_px"] = f
        score *= _goodness(f, s["flow_px"])
    score = np.where(has, np.clip(score, 0.0, 1.0), np.nan)
    if is_reference is not None:
        score = np.where(np.asarray(is_reference, dtype=bool) & has, 1.0, score)
    return FrameScores(score=score, terms=terms)


def worst_order(score: np.ndarray, exclude: Iterable[int] = ()) -> np.ndarray:
    """Frames with a score, by increasing score (ties by frame index), ``exclude`` left out."""
    score = np.asarray(score, dtype=np.float64)
    ok = np.isfinite(score)
    ex = np.fromiter((int(f) for f in exclude), dtype=np.int64)
    ok[ex[(ex >= 0) & (ex < len(score))]] = False
    frames = np.flatnonzero(ok)
    return frames[np.lexsort((frames, score[frames]))]


def next_worst(
    score: np.ndarray, current: int | None = None, exclude: Iterable[int] = ()
) -> int | None:
    """The next frame after ``current`` in :func:`worst_order` (the worst one if ``current`` is
    None or not in the order; None when there is nothing to review)."""
    order = worst_order(score, exclude)
    if order.size == 0:
        return None
    if current is not None:
        hit = np.flatnonzero(order == int(current))
        if hit.size and hit[0] + 1 < order.size:
            return int(order[hit[0] + 1])
        if hit.size:
            return int(order[0])  # wrapped around
    return int(order[0])


# =============================================================================================
# review edits


def seed_annotation(
    joints_mm: np.ndarray,
    camera: CameraIntrinsics,
    depth_mm: np.ndarray | None = None,
    surface_offsets_mm: np.ndarray | None = None,
    margin_mm: float = 10.0,
) -> FrameAnnotation:
    """A reference annotation from a shown skeleton ``(J, 3)`` mm: every joint placed in 3D (and its
    projection in 2D), visibility by a depth test against ``depth_mm`` (H, W) when given."""
    x = np.asarray(joints_mm, dtype=np.float64)
    nj = len(x)
    ann = FrameAnnotation.empty(nj)
    ann.xyz_mm[:] = x
    ann.uv_px[:] = camera.project(x)
    if depth_mm is not None:
        uv = np.rint(ann.uv_px).astype(np.int64)
        inside = (
            (uv[:, 0] >= 0)
            & (uv[:, 0] < camera.width)
            & (uv[:, 1] >= 0)
            & (uv[:, 1] < camera.height)
        )
        d = np.zeros(nj)
        d[inside] = depth_mm[uv[inside, 1], uv[inside, 0]]
        off = (
            0.0 if surface_offsets_mm is None else np.asarray(surface_offsets_mm, dtype=np.float64)
        )
        ann.visible[:] = inside & (d > 0) & (d >= x[:, 2] - off - margin_mm)
    return ann


def correction_command(
    session: Session,
    frame: int,
    joint: int,
    xyz_mm: np.ndarray,
    shown_mm: np.ndarray,
    depth_mm: np.ndarray | None = None,
) -> tuple[Command, bool]:
    """The command of a review edit of ``joint`` on ``frame`` to ``xyz_mm`` (mm, camera frame).

    Returns ``(command, became_reference)``. On a frame that is already an annotated reference it is
    a single :class:`SetJoint3D`. Otherwise one :class:`Batch`: ``SetReference(is_reference=True,
    correction=True)`` (unless it is a selected reference without annotation), the frame's
    annotation seeded from ``shown_mm`` (J, 3) (:func:`seed_annotation`) and the joint edit.
    Call it under ``session.lock`` together with ``session.execute`` so that two annotators
    correcting the same frame at once cannot seed over each other's joints.
    """
    xyz = tuple(round(float(v), 2) for v in np.asarray(xyz_mm, dtype=np.float64))
    edit = SetJoint3D(frame=int(frame), joint=int(joint), xyz_mm=xyz)  # type: ignore[arg-type]
    is_ref = int(frame) in set(session.model.selection.reference_frames)
    if is_ref and session.annotation(int(frame)) is not None:
        return edit, False
    commands: list[dict[str, Any]] = []
    if not is_ref:
        commands.append(
            SetReference(frame=int(frame), is_reference=True, correction=True).model_dump()
        )
    seed = seed_annotation(shown_mm, session.camera, depth_mm, session.skeleton.surface_offsets_mm)
    commands.append(SetFrameAnnotation(frame=int(frame), annotation=seed.to_json()).model_dump())
    commands.append(edit.model_dump())
    return Batch(commands=commands), not is_ref


# =============================================================================================
# live results


class LiveResults:
    """The skeleton of every frame as the review view shows it, thread-safe.

    ``joints_mm`` (N, J, 3): the best stage on disk (refined, else propagated, else lifted), then
    overwritten frame by frame by a running job; ``confidence`` (N, J); ``stage`` (N,) int8
    (0 none, 1 lifted, 2 propagated, 3 refined); ``version`` grows with every change.
    """

    def __init__(self, session: Session):
        self.session = session
        self._lock = threading.Lock()
        self.version = 0
        self._score_cache: tuple[int, FrameScores] | None = None
        self._crops: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self.reload()

    def reload(self) -> None:
        from handanno_core.export import best_joints

        results = self.session.load_results()
        joints, stage = best_joints(results)
        with self._lock:
            self.joints_mm = joints
            self.stage = stage
            self.confidence = np.array(results["confidence"], dtype=np.float64)
            self.bone_lengths_mm = (
                None
                if self.session.model.bone_lengths_mm is None
                else np.asarray(self.session.model.bone_lengths_mm, dtype=np.float64)
            )
            self.version += 1

    def put(
        self, frame: int, joints_mm: np.ndarray, confidence: np.ndarray | None, stage: int
    ) -> None:
        with self._lock:
            self.joints_mm[frame] = joints_mm
            if confidence is not None:
                self.confidence[frame] = confidence
            self.stage[frame] = stage
            self.version += 1

    def put_all(self, joints_mm: np.ndarray, stage: int) -> None:
        ok = np.all(np.isfinite(joints_mm), axis=(1, 2))
        with self._lock:
            self.joints_mm[ok] = joints_mm[ok]
            self.stage[ok] = stage
            self.version += 1

    def frame(self, frame: int) -> tuple[np.ndarray, int]:
        with self._lock:
            return self.joints_mm[frame].copy(), int(self.stage[frame])

    def filled(self) -> int:
        with self._lock:
            return int((self.stage > 0).sum())

    def _crop_data(self):
        if self._crops is None:
            from handanno_core.session import CROPS_FILE, CROPS_META_FILE

            folder = self.session.folder
            if not (folder / CROPS_FILE).exists() or not (folder / CROPS_META_FILE).exists():
                return None  # never compute crops from the UI; the depth term is skipped
            with np.load(folder / CROPS_META_FILE) as meta:
                centres, boxes = meta["centres_mm"], meta["boxes"]
            crops = np.load(folder / CROPS_FILE, mmap_mode="r")
            if len(crops) != self.session.num_frames:
                return None
            self._crops = (crops, boxes, centres)
        return self._crops

    def scores(self) -> FrameScores:
        """:func:`frame_scores` of the current skeletons (cached per version)."""
        cached = self._score_cache
        if cached is not None and cached[0] == self.version:
            return cached[1]
        with self._lock:
            version = self.version
            joints = self.joints_mm.copy()
            conf = self.confidence.copy()
            bones_mm = self.bone_lengths_mm
        session = self.session
        skeleton = session.skeleton
        is_ref = np.zeros(session.num_frames, dtype=bool)
        is_ref[session.reference_frames] = True
        residual = None
        crop_data = self._crop_data()
        if crop_data is not None:
            crops, boxes, centres = crop_data
            residual = depth_residuals(
                joints,
                crops,
                boxes,
                centres,
                session.camera,
                cube_mm=session.model.settings.cube_mm,
                surface_offsets_mm=np.asarray(skeleton.surface_offsets_mm),
            )
        result = frame_scores(
            conf,
            joints,
            skeleton.bones,
            bones_mm,
            depth_residual_mm=residual,
            sequence_breaks=session.model.sequence_breaks,
            is_reference=is_ref,
        )
        self._score_cache = (version, result)
        return result


# =============================================================================================
# the background job


class Cancelled(Exception):
    """Raised inside the stage callbacks to stop a job."""


def refine_all(
    session: Session, progress: Callable[[int, float], None] | None = None
) -> np.ndarray:
    """Global refinement of the session's current results; returns ``final_mm`` (N, J, 3) mm
    without saving it (the runner saves it with propagation's results, in one replace)."""
    from handanno_core.pipeline import refine

    result = refine(session, progress=progress, save=False, quiet=True)
    return np.asarray(result.joints_mm, dtype=np.float64)


@dataclass
class JobStatus:
    kind: str = ""  # "full" | "corrections" | "lift"
    #: idle | lift-all | lift | propagate | refine | saving | done | cancelled | failed
    phase: str = "idle"
    done: int = 0
    total: int = 0
    message: str = ""
    frames: list[int] = field(default_factory=list)  # frames the job recomputes
    started_at: float = 0.0
    finished_at: float = 0.0

    @property
    def running(self) -> bool:
        return self.phase in ("lift-all", "lift", "propagate", "refine", "saving", "starting")

    @property
    def percent(self) -> float:
        if self.phase == "refine":
            return 90.0 + 10.0 * min(self.done / max(self.total, 1), 1.0)
        if self.phase in ("saving", "done"):
            return 100.0
        return 90.0 * self.done / self.total if self.total else 0.0

    def text(self) -> str:
        if self.phase == "propagate":
            return f"propagating: {self.done} of {self.total} frames"
        if self.phase == "refine":
            return f"refining: iteration {self.done}"
        if self.phase == "lift":
            return f"lifting corrected frame(s) {self.message}"
        if self.phase == "lift-all":
            return (
                f"lifting references, estimating bone lengths: {self.done} of {self.total}"
                if self.total
                else "lifting references, estimating bone lengths"
            )
        return self.message or self.phase


LiftFor = Callable[[int, int], "np.ndarray | None"]


class ReviewRunner:
    """Runs "propagate & refine" jobs on one background thread; see the module docstring.

    ``propagate_fn`` / ``refine_fn`` default to :func:`handanno_core.pipeline.propagate` and
    :func:`refine_all` (tests inject slower or faster ones). ``lift_for(frame, min_seq)`` returns the
    lifted joints (J, 3) of a corrected frame reflecting journal entry ``min_seq`` or later (the app
    waits for its lift worker); without it the frame is lifted here with ``lift_frame``.
    ``lift_all_fn`` (default :func:`handanno_core.pipeline.lift`) lifts every annotated reference
    and stores the bone lengths. ``listeners`` are called as ``listener(event, runner, frame)``
    with event ``"progress"``, ``"frame"`` (a new skeleton for ``frame``), ``"lifted"`` (lift all
    saved new reference poses) or ``"finished"``.
    """

    def __init__(
        self,
        session: Session,
        live: LiveResults | None = None,
        *,
        propagate_fn: Callable[..., Any] | None = None,
        refine_fn: Callable[..., np.ndarray] | None = None,
        lift_for: LiftFor | None = None,
        lift_all_fn: Callable[..., Any] | None = None,
        workers: int = 1,
        checkpoint_every_s: float = 5.0,
        debounce_s: float = 1.0,
    ):
        self.session = session
        self.live = live if live is not None else LiveResults(session)
        if propagate_fn is None:
            from handanno_core.pipeline import propagate as propagate_fn
        self.propagate_fn = propagate_fn
        self.refine_fn = refine_fn or refine_all
        if lift_all_fn is None:
            from handanno_core.pipeline import lift as lift_all_fn
        self.lift_all_fn = lift_all_fn
        self.lift_for = lift_for
        self.workers = workers
        self.checkpoint_every_s = checkpoint_every_s
        self.debounce_s = debounce_s
        self.status = JobStatus()
        self.listeners: list[Callable[[str, ReviewRunner, int], None]] = []
        self.history: list[JobStatus] = []
        self._cond = threading.Condition()
        self._cancel = threading.Event()
        self._pending_full = False
        self._pending_lift = False
        self._pending_corrections: dict[int, int] = {}  # frame -> journal seq of the edit
        self._corrections_due = 0.0
        self._stop = False
        self._thread = threading.Thread(target=self._run, name="handanno-review", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ requests
    def start_full(self) -> bool:
        """Queue a full run (propagate every frame, then refine). False if one is running/queued."""
        with self._cond:
            if self.status.running or self._pending_full:
                return False
            self._pending_full = True
            self._cancel.clear()
            self.status = JobStatus(
                kind="full", phase="starting", message="starting", started_at=time.time()
            )
            self._cond.notify_all()
        self._emit("progress", -1)
        return True

    def start_lift(self) -> bool:
        """Queue "lift all" (every annotated reference, bone lengths re-estimated). False if a
        job is running or queued."""
        with self._cond:
            if self.status.running or self._pending_full or self._pending_lift:
                return False
            self._pending_lift = True
            self._cancel.clear()
            self.status = JobStatus(
                kind="lift", phase="starting", message="starting", started_at=time.time()
            )
            self._cond.notify_all()
        self._emit("progress", -1)
        return True

    def needs_lift(self) -> bool:
        """True if a full run must lift first: no bone lengths yet, or an annotated reference
        without a lifted pose."""
        session = self.session
        if session.model.bone_lengths_mm is None:
            return True
        lifted = session.load_results()["lifted_mm"]
        annotated = [
            f for f, a in session.annotations(session.reference_frames).items() if a.annotated.any()
        ]
        return not np.all(np.isfinite(lifted[annotated]))

    def request_correction(self, frame: int, seq: int) -> None:
        """A review edit made ``frame`` a reference (journal entry ``seq``): re-propagate and refine
        its descendants once edits have been quiet for ``debounce_s``."""
        with self._cond:
            self._pending_corrections[int(frame)] = max(
                int(seq), self._pending_corrections.get(int(frame), 0)
            )
            self._corrections_due = time.monotonic() + self.debounce_s
            self._cond.notify_all()

    def cancel(self) -> None:
        """Stop the running job (the session keeps its old results); drop queued corrections."""
        with self._cond:
            self._pending_full = False
            self._cancel.set()
            self._cond.notify_all()

    def wait_idle(self, timeout: float = 60.0) -> bool:
        deadline = time.monotonic() + timeout
        with self._cond:
            while (
                self._pending_full
                or self._pending_lift
                or self._pending_corrections
                or self.status.running
            ):
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(min(left, 0.2))
        return True

    def stop(self, timeout: float = 10.0) -> None:
        with self._cond:
            self._stop = True
            self._cancel.set()
            self._cond.notify_all()
        self._thread.join(timeout)

    # ------------------------------------------------------------------ thread
    def _emit(self, event: str, frame: int) -> None:
        for listener in list(self.listeners):
            try:
                listener(event, self, frame)
            except Exception:
                traceback.print_exc()

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._stop:
                    if self._pending_full or self._pending_lift:
                        break
                    if self._pending_corrections and time.monotonic() >= self._corrections_due:
                        break
                    timeout = None
                    if self._pending_corrections:
                        timeout = max(self._corrections_due - time.monotonic(), 0.01)
                    self._cond.wait(timeout)
                if self._stop:
                    return
                if self._pending_full:
                    self._pending_full = False
                    kind, corrections = "full", {}
                    self._pending_corrections.clear()
                elif self._pending_lift:
                    self._pending_lift = False
                    kind, corrections = "lift", {}
                else:
                    kind, corrections = "corrections", dict(self._pending_corrections)
                    self._pending_corrections.clear()
                    self._cancel.clear()
                    self.status = JobStatus(kind=kind, phase="starting", started_at=time.time())
            try:
                self._job(kind, corrections)
            except Cancelled:
                self._finish("cancelled", "cancelled: the session keeps its previous results")
            except Exception as exc:
                traceback.print_exc()
                self._finish("failed", f"failed: {type(exc).__name__}: {exc}")

    def _set(self, **kw: Any) -> None:
        for k, v in kw.items():
            setattr(self.status, k, v)
        self._emit("progress", -1)

    def _finish(self, phase: str, message: str) -> None:
        self._remove_partial()
        with self._cond:
            self.status.phase = phase
            self.status.message = message
            self.status.finished_at = time.time()
            self.history.append(JobStatus(**vars(self.status)))
            self._cond.notify_all()
        self.live.reload()
        self._emit("finished", -1)

    def _check(self) -> None:
        if self._cancel.is_set():
            raise Cancelled

    def _remove_partial(self) -> None:
        (self.session.folder / PARTIAL_FILE).unlink(missing_ok=True)

    def _lift_all(self) -> None:
        """Lift every annotated reference and estimate the bone lengths (saved on success only)."""
        self._set(phase="lift-all", done=0, total=0, message="")

        def progress(done: int, total: int) -> None:
            self._check()
            self._set(done=int(done), total=int(total))

        self.lift_all_fn(self.session, workers=self.workers, quiet=True, progress=progress)
        self.live.reload()
        self._emit("lifted", -1)

    def _job(self, kind: str, corrections: dict[int, int]) -> None:
        from handanno_core.propagate import descendants

        session = self.session
        if kind == "lift":
            self._lift_all()
            self._finish("done", "done: references lifted, bone lengths estimated")
            return
        if kind == "full" and self.needs_lift():
            self._lift_all()
        frames: np.ndarray | None = None
        if corrections:
            self._set(phase="lift", message=", ".join(map(str, sorted(corrections))))
            for frame, seq in sorted(corrections.items()):
                self._check()
                joints, conf = self._lift(frame, seq)
                with session.lock:
                    results = session.load_results()
                    results["lifted_mm"][frame] = joints
                    results["confidence"][frame] = conf
                    session.save_results(
                        lifted_mm=results["lifted_mm"], confidence=results["confidence"]
                    )
                self.live.put(frame, joints, conf, 1)
                self._emit("frame", frame)
            frames = descendants(session.parent, sorted(corrections))
        parent = session.parent
        todo = np.flatnonzero(parent >= 0) if frames is None else frames[parent[frames] >= 0]
        self._set(
            phase="propagate", done=0, total=len(todo), frames=[int(f) for f in todo], message=""
        )
        shape = (session.num_frames, session.skeleton.num_joints)
        partial_init = np.full((*shape, 3), np.nan)
        partial_conf = np.full(shape, np.nan)
        last_checkpoint = time.monotonic()

        def on_result(frame: int, joints: np.ndarray, conf: np.ndarray) -> None:
            nonlocal last_checkpoint
            self._check()
            partial_init[frame] = joints
            partial_conf[frame] = conf
            self.live.put(
                int(frame),
                np.asarray(joints, dtype=np.float64),
                np.asarray(conf, dtype=np.float64),
                2,
            )
            self._emit("frame", int(frame))
            if time.monotonic() - last_checkpoint >= self.checkpoint_every_s:
                last_checkpoint = time.monotonic()
                # Periodic save of what is computed so far, next to (never over) results.npz.
                atomic_save_npz(
                    session.folder / PARTIAL_FILE,
                    {"init_mm": partial_init, "confidence": partial_conf},
                )

        def progress(done: int, total: int) -> None:
            self._check()
            self._set(done=int(done), total=int(total))

        # issue 16: propagation's init_mm and refinement's final_mm reach results.npz together in
        # one atomic replace (session.staged_results), so a cancel, an error or a kill at any
        # instant leaves results.npz exactly as it was before the job.
        with session.staged_results():
            if len(todo):
                self.propagate_fn(
                    session,
                    workers=self.workers,
                    frames=None if frames is None else frames,
                    progress=progress,
                    on_result=on_result,
                    quiet=True,
                )
            self._check()
            self._set(phase="refine", done=0, total=30, message="")

            def refine_progress(iteration: int, energy: float) -> None:
                self._check()
                self._set(done=int(iteration))

            final = self.refine_fn(session, progress=refine_progress)
            self._check()
            self._set(phase="saving")
            session.save_results(final_mm=final)
        self.live.put_all(final, 3)
        n = len(todo)
        self._finish("done", f"done: {n} frame(s) propagated, all frames refined")

    def _lift(self, frame: int, seq: int) -> tuple[np.ndarray, np.ndarray]:
        if self.lift_for is not None:
            joints = self.lift_for(frame, seq)
            if joints is not None:
                joints = np.asarray(joints, dtype=np.float64)
                return joints, np.ones(len(joints))
        from handanno_core.lift import lift_frame

        session = self.session
        ann = session.annotation(frame)
        if ann is None:
            raise SessionError(f"frame {frame} has no annotation to lift")
        depth = np.asarray(session.open_sequence().depth(frame), dtype=np.float32)
        bones = session.model.bone_lengths_mm
        if bones is None:
            bones = session.skeleton.template_bone_lengths_mm
        result = lift_frame(
            ann,
            depth,
            session.camera,
            session.skeleton,
            np.asarray(bones, dtype=np.float64),
            eps_mm=session.model.settings.eps_mm,
            angle_limits=session.model.settings.angle_limits,
            init_mm=np.nan_to_num(ann.xyz_mm) if np.all(np.isfinite(ann.xyz_mm)) else None,
        )
        return np.asarray(result.joints_mm, dtype=np.float64), np.asarray(
            result.confidence, dtype=np.float64
        )
