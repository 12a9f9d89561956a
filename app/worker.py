"""The engine off the UI thread: a background thread that re-lifts edited frames.

``LiftWorker.submit(frame)`` never blocks: it puts the frame in a queue, and a newer job for a
frame that is still pending replaces the pending one (coalescing), so a burst of edits on one
frame costs one lift. The annotation is read from the session when the job *starts*, so the
result always reflects the newest edits. Results go to ``on_result(frame, LiftOutcome)``
(called on the worker thread) and are kept in ``latest`` (warm start for the next lift of the
frame; the first lift of a frame starts from ``initial_guess(frame)``, the app's pre-fill). Lifted joints are written to ``results.npz`` (``lifted_mm``, ``confidence``) when the
queue has been idle for ``save_after_s`` seconds.
"""

from __future__ import annotations

import functools
import threading
import time
import traceback
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from handanno_core.session import Session

from .frames import FrameStore

LiftFunction = Callable[..., object]


#: SLSQP iterations of the live re-lift while a joint is edited (measured on the demo: hard solves
#: converge in 13-28 iterations at ~0.9 ms each, elastic ones in 16-22 at ~2.5 ms each, since their
#: slacks add 21 variables and 46 rows). The preview stops at 30 where a solve would take longer
#: (a frame with only its first joints placed; `handanno lift` re-solves every reference to
#: convergence), which keeps the slowest elastic preview under 100 ms. A frame whose lift needed
#: slack (a 2D point off the finger reads the surface behind it) is re-lifted in elastic mode
#: directly, skipping a hard solve that would fail again, with slacks on the joints that needed
#: them only (~20 ms instead of ~50 ms).
LIVE_MAX_ITER = 30


def default_lift_function() -> LiftFunction | None:
    """``handanno_core.lift.lift_frame`` with a bounded iteration count for live previews."""
    from handanno_core.lift import lift_frame

    return functools.partial(lift_frame, max_iter=LIVE_MAX_ITER)


@dataclass
class LiftOutcome:
    frame: int
    joints_mm: np.ndarray | None  # (J, 3) mm, None on failure
    confidence: np.ndarray | None  # (J,)
    error: str | None
    journal_seq: int  # the session's journal position the lift saw
    submitted_at: float  # perf_counter() of the (latest) submit
    finished_at: float  # perf_counter() when the lift returned
    duration_s: float
    slack_joints: tuple[int, ...] = ()  # joints whose depth interval could not be met

    @property
    def needed_slack(self) -> bool:
        return bool(self.slack_joints)


class LiftWorker:
    """One daemon thread lifting frames for the app; see the module docstring."""

    def __init__(
        self,
        session: Session,
        frames: FrameStore,
        lift_fn: LiftFunction | None = None,
        on_result: Callable[[int, LiftOutcome], None] | None = None,
        save_after_s: float = 3.0,
        initial_guess: Callable[[int], np.ndarray | None] | None = None,
    ):
        self.session = session
        self.frames = frames
        self.lift_fn = lift_fn if lift_fn is not None else default_lift_function()
        self.on_result = on_result
        self.save_after_s = save_after_s
        #: frame -> (J, 3) mm start of a frame's first lift (the pre-fill), or None
        self.initial_guess = initial_guess
        self.latest: dict[int, LiftOutcome] = {}
        self._pending: OrderedDict[int, float] = OrderedDict()
        self._cond = threading.Condition()
        self._stop = False
        self._busy = False
        self._dirty = False
        self.jobs_done = 0
        self.jobs_coalesced = 0
        self._thread = threading.Thread(target=self._run, name="handanno-lift", daemon=True)

    @property
    def available(self) -> bool:
        return self.lift_fn is not None

    def start(self) -> LiftWorker:
        self._thread.start()
        return self

    def stop(self, timeout: float = 5.0) -> None:
        with self._cond:
            self._stop = True
            self._cond.notify_all()
        if self._thread.is_alive():
            self._thread.join(timeout)
        self._save_results()

    def submit(self, frame: int) -> None:
        """Queue a lift of ``frame`` (replacing a pending one for the same frame). Never blocks."""
        if self.lift_fn is None:
            return
        with self._cond:
            if frame in self._pending:
                self.jobs_coalesced += 1
            self._pending[frame] = time.perf_counter()
            self._cond.notify()

    def forget(self, frames: list[int] | np.ndarray) -> None:
        """Drop the live lifts of ``frames`` (their lifted joints on disk were replaced, e.g. by
        "lift all"): the next save does not write these previews back, and the next edit or view
        of such a frame lifts it afresh. Called under the session lock by the caller's choice."""
        with self.session.lock:
            for f in frames:
                self.latest.pop(int(f), None)

    def wait_idle(self, timeout: float = 10.0) -> bool:
        """Block until no job is pending or running (tests and benchmarks only)."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while self._pending or self._busy:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(left)
        return True

    # ------------------------------------------------------------------ thread
    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._pending and not self._stop:
                    if self._dirty:
                        if not self._cond.wait(self.save_after_s) and not self._pending:
                            break  # idle long enough: save below
                    else:
                        self._cond.wait()
                if self._stop:
                    return
                if not self._pending:
                    job = None
                else:
                    frame, submitted = self._pending.popitem(last=False)
                    job = (frame, submitted)
                    self._busy = True
            if job is None:
                self._save_results()
                continue
            try:
                outcome = self._lift(*job)
                self.latest[outcome.frame] = outcome
                self.jobs_done += 1
                if outcome.joints_mm is not None:
                    self._dirty = True
                if self.on_result is not None:
                    try:
                        self.on_result(outcome.frame, outcome)
                    except Exception:
                        traceback.print_exc()
            finally:
                with self._cond:
                    self._busy = False
                    self._cond.notify_all()

    def _lift(self, frame: int, submitted: float) -> LiftOutcome:
        t0 = time.perf_counter()
        session = self.session
        with session.lock:
            annotation = session.annotation(frame)
            seq = session.model.journal_seq
            bones = session.model.bone_lengths_mm
            settings = session.model.settings
        skeleton = session.skeleton

        def fail(msg: str) -> LiftOutcome:
            now = time.perf_counter()
            return LiftOutcome(frame, None, None, msg, seq, submitted, now, now - t0)

        if annotation is None or not annotation.annotated.any():
            return fail("nothing annotated yet")
        data = self.frames.get(frame)
        if data.depth is None:
            return fail(data.error or "no depth")
        if bones is None:
            if skeleton.template_bone_lengths_mm is None:
                return fail(f"skeleton {skeleton.name} has no template bone lengths")
            bones = skeleton.template_bone_lengths_mm
        previous = self.latest.get(frame)
        init = (
            previous.joints_mm if previous is not None and previous.joints_mm is not None else None
        )
        if init is None and self.initial_guess is not None:
            init = self.initial_guess(frame)  # first lift of the frame: start hand-shaped
        slack_joints = previous.slack_joints if previous is not None else ()
        try:
            result = self.lift_fn(
                annotation,
                data.depth,
                session.camera,
                skeleton,
                np.asarray(bones, dtype=np.float64),
                eps_mm=settings.eps_mm,
                angle_limits=settings.angle_limits,
                init_mm=init,
                start_elastic=bool(slack_joints),
                elastic_joints=np.asarray(slack_joints, dtype=np.int64),
            )
        except Exception as exc:
            traceback.print_exc()
            return fail(f"lifting failed: {exc}")
        joints = np.asarray(result.joints_mm, dtype=np.float64)  # type: ignore[attr-defined]
        conf = np.asarray(getattr(result, "confidence", np.ones(len(joints))), dtype=np.float64)
        now = time.perf_counter()
        slack = tuple(int(k) for k in getattr(result, "slack_joints", ()))
        return LiftOutcome(frame, joints, conf, None, seq, submitted, now, now - t0, slack)

    def _save_results(self) -> None:
        """Write lifted joints of every frame lifted so far into results.npz (atomic)."""
        if not self._dirty:
            return
        self._dirty = False
        try:
            # Read-modify-write under the session lock, so a concurrent propagation save (review
            # runner) is never overwritten with stale arrays, and frames dropped by forget() are
            # not written back.
            with self.session.lock:
                lifted = {f: o for f, o in list(self.latest.items()) if o.joints_mm is not None}
                if not lifted:
                    return
                current = self.session.load_results()
                lifted_mm, conf = current["lifted_mm"], current["confidence"]
                for f, o in lifted.items():
                    lifted_mm[f] = o.joints_mm
                    conf[f] = o.confidence
                self.session.save_results(lifted_mm=lifted_mm, confidence=conf)
        except Exception:
            traceback.print_exc()
