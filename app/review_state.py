"""The app side of review: live results streamed while a job runs, and the background job that
propagates and refines. The review engine (scores, "next worst frame", review edits) lives in
:mod:`handanno_core.review` (no viser; the bench's review loop uses it too) and is re-exported here
under its old names.

* :class:`LiveResults` - the joints shown by the review view, updated frame by frame while a job
  runs (``on_result``), thread-safe; :meth:`LiveResults.scores` ranks them.
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
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from handanno_core.review import (  # noqa: F401  (re-exported: the app's and tests' names)
    OFF_HAND_MM,
    SCORE_SCALES,
    FrameScores,
    bone_anomaly,
    correction_command,
    depth_residuals,
    frame_scores,
    next_worst,
    seed_annotation,
    session_scores,
    temporal_jump,
    worst_order,
)
from handanno_core.session import Session, SessionError, atomic_save_npz

PARTIAL_FILE = "propagation_partial.npz"


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

    def scores(self) -> FrameScores:
        """:func:`~handanno_core.review.session_scores` of the current skeletons (cached per
        version; the depth term only when the session's crops are cached on disk)."""
        cached = self._score_cache
        if cached is not None and cached[0] == self.version:
            return cached[1]
        with self._lock:
            version = self.version
            joints = self.joints_mm.copy()
            conf = self.confidence.copy()
            bones_mm = self.bone_lengths_mm
        if self._crops is None:
            from handanno_core.prefill import cached_crops

            self._crops = cached_crops(self.session)  # never computed from the UI
        result = session_scores(self.session, joints, conf, self._crops, bone_lengths_mm=bones_mm)
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
