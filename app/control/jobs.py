"""The app's background jobs (no viser): the live lift worker, the review runner, and the ONE
adapter from a session to the guesses' refit (:func:`lift_for_session`, calling
:func:`handanno_core.guesses.refit_guesses`) both use.

**LiftWorker** re-lifts edited frames.

``LiftWorker.submit(frame)`` never blocks: it puts the frame in a queue, and a newer job for a
frame that is still pending replaces the pending one (coalescing), so a burst of edits on one
frame costs one lift. The annotation is read from the session when the job *starts*, so the
result always reflects the newest edits. Results go to ``on_result(frame, LiftOutcome)``
(called on the worker thread) and are kept in ``latest`` (warm start for the next lift of the
frame; the first lift of a frame starts from ``initial_guess(frame)``, the app's pre-fill). Lifted joints are written to ``results.npz`` (``lifted_mm``, ``confidence``) when the
queue has been idle for ``save_after_s`` seconds.

**ReviewRunner** runs "propagate & refine" jobs on one background thread: a full run, or after
review corrections only the frames that depend on the corrected ones (their descendants in the
propagation's forests, :func:`handanno_core.pipeline.frames_to_repropagate`); and "lift all"
(:func:`handanno_core.pipeline.lift`: every annotated reference, bone lengths estimated), which a
full run does first when the session has no bone lengths or an annotated reference has no lifted
pose (a session annotated only in the browser). Cancelling leaves ``results.npz`` either as it
was (or as the finished lift left it) or completely new (never half-written) and never touches
the journal.
"""

from __future__ import annotations

import threading
import time
import traceback
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from handanno_core.results import Stage, update_lifted
from handanno_core.session import Session, SessionError, atomic_save_npz

from .frames import FrameStore
from .live import LiveResults

LiftFunction = Callable[..., object]


def default_lift_function() -> LiftFunction | None:
    """The live lift: :func:`handanno_core.guesses.live_lift_function` (``lift_frame`` bounded to
    ``LIVE_MAX_ITER`` iterations)."""
    from handanno_core.guesses import live_lift_function

    return live_lift_function()


class LiftUnavailable(ValueError):
    """A frame cannot be lifted yet (nothing annotated, no bone lengths); the message says why."""


@dataclass(frozen=True)
class WarmStart:
    """Where a lift starts: ``init_mm`` (J, 3) mm, the frame's previous lift (None: first lift),
    ``prefill_mm`` (J, 3) mm, the frame's pre-fill (the start of a first lift; None: none), and
    whether it starts elastic with slack on ``elastic_joints`` (the joints the previous lift
    needed it on)."""

    init_mm: np.ndarray | None = None
    start_elastic: bool = False
    elastic_joints: tuple[int, ...] = ()
    prefill_mm: np.ndarray | None = None


def lift_for_session(
    session: Session,
    frame: int,
    depth: np.ndarray,
    *,
    lift_fn: LiftFunction | None = None,
    warm_start: WarmStart = WarmStart(),
    guess_model: dict | None = None,
) -> tuple[np.ndarray, np.ndarray, tuple[int, ...], int]:
    """Lift ``frame``'s current annotation on ``depth`` (H, W) mm with the session's bone lengths
    (the skeleton's template ones before ``lift all`` estimated them), eps and angle limits: THE
    adapter from a session to :func:`handanno_core.guesses.refit_guesses` (the refit of the
    guesses the bench's interactive annotator uses too) of the app (live lift worker, review
    corrections). ``guess_model``: ``{"hand_model", "observation"}`` of the frame
    (:func:`handanno_core.prefill.guess_model`): the unplaced joints are fitted to its points.

    Returns ``(joints (J, 3) mm, confidence (J,), slack joints, journal seq the lift saw)``.
    Raises :class:`LiftUnavailable` when nothing is annotated or no bone lengths exist.
    """
    from handanno_core.guesses import refit_guesses

    if lift_fn is None:  # review corrections: solved to convergence
        from handanno_core.lift import lift_frame as lift_fn
    with session.lock:
        annotation = session.annotation(frame)
        seq = session.model.journal_seq
        bones = session.bone_lengths_of(frame)  # its hand's (several hands), else the session's
        settings = session.model.settings
    skeleton = session.skeleton
    if annotation is None or not annotation.annotated.any():
        raise LiftUnavailable("nothing annotated yet")
    if bones is None:
        if skeleton.template_bone_lengths_mm is None:
            raise LiftUnavailable(f"skeleton {skeleton.name} has no template bone lengths")
        bones = skeleton.template_bone_lengths_mm
    fit = refit_guesses(
        annotation,
        depth,
        session.camera,
        skeleton,
        np.asarray(bones, dtype=np.float64),
        eps_mm=settings.eps_mm,
        angle_limits=settings.angle_limits,
        prefill_mm=warm_start.prefill_mm,
        previous_mm=warm_start.init_mm,
        start_elastic=warm_start.start_elastic,
        elastic_joints=warm_start.elastic_joints,
        lift_fn=lift_fn,
        **(guess_model or {}),
    )
    return fit.joints_mm, fit.confidence, fit.slack_joints, seq


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
        guess_model: Callable[[int], dict] | None = None,
    ):
        self.session = session
        self.frames = frames
        self.lift_fn = lift_fn if lift_fn is not None else default_lift_function()
        self.on_result = on_result
        self.save_after_s = save_after_s
        #: frame -> (J, 3) mm start of a frame's first lift (the pre-fill), or None
        self.initial_guess = initial_guess
        #: frame -> {"hand_model", "observation"} the refits of a frame fit its guesses with
        #: (:func:`handanno_core.prefill.guess_model`; computed at the frame's first lift)
        self.guess_model = guess_model
        self._guess_models: dict[int, dict] = {}
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
                self._guess_models.pop(int(f), None)

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
        seq = self.session.model.journal_seq
        data = self.frames.get(frame)
        previous = self.latest.get(frame)
        init = (
            previous.joints_mm if previous is not None and previous.joints_mm is not None else None
        )
        prefill = None
        if init is None and self.initial_guess is not None:
            prefill = self.initial_guess(frame)  # first lift of the frame: start hand-shaped
        if init is None and self.guess_model is not None:
            self._guess_models[frame] = self._safe_guess_model(frame)
        slack = previous.slack_joints if previous is not None else ()
        try:
            if data.depth is None:
                raise LiftUnavailable(data.error or "no depth")
            joints, conf, slack, seq = lift_for_session(
                self.session,
                frame,
                data.depth,
                lift_fn=self.lift_fn,
                warm_start=WarmStart(init, bool(slack), tuple(slack), prefill),
                guess_model=self._guess_models.get(frame),
            )
        except LiftUnavailable as exc:
            now = time.perf_counter()
            return LiftOutcome(frame, None, None, str(exc), seq, submitted, now, now - t0)
        except Exception as exc:
            traceback.print_exc()
            now = time.perf_counter()
            msg = f"lifting failed: {exc}"
            return LiftOutcome(frame, None, None, msg, seq, submitted, now, now - t0)
        now = time.perf_counter()
        return LiftOutcome(frame, joints, conf, None, seq, submitted, now, now - t0, slack)

    def _safe_guess_model(self, frame: int) -> dict:
        """:attr:`guess_model` of ``frame``; ``{}`` (plain refits) if it fails."""
        try:
            return self.guess_model(frame)
        except Exception:
            traceback.print_exc()
            return {}

    def _save_results(self) -> None:
        """Write lifted joints of every frame lifted so far into results.npz (atomic; frames
        dropped by forget() are not written back)."""
        if not self._dirty:
            return
        self._dirty = False
        try:
            with self.session.lock:
                update_lifted(
                    self.session,
                    {
                        f: (o.joints_mm, o.confidence)
                        for f, o in list(self.latest.items())
                        if o.joints_mm is not None
                    },
                )
        except Exception:
            traceback.print_exc()


# =============================================================================================
# the review runner: propagate & refine, lift all

PARTIAL_FILE = "propagation_partial.npz"


class Cancelled(Exception):
    """Raised inside the stage callbacks to stop a job."""


def refine_all(
    session: Session,
    progress: Callable[[int, float], None] | None = None,
    frames: np.ndarray | None = None,
) -> np.ndarray:
    """Global refinement of the session's current results; returns ``final_mm`` (N, J, 3) mm
    without saving it (the runner saves it with propagation's results, in one replace).
    ``frames``: refine only these, every other refined frame keeps its result
    (:func:`handanno_core.pipeline.refine`)."""
    from handanno_core.pipeline import refine

    result = refine(session, progress=progress, save=False, quiet=True, frames=frames)
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
        return self._queue("full")

    def start_lift(self) -> bool:
        """Queue "lift all" (every annotated reference, bone lengths re-estimated). False if a
        job is running or queued."""
        return self._queue("lift")

    def _queue(self, kind: str) -> bool:
        with self._cond:
            busy = self._pending_full or (kind == "lift" and self._pending_lift)
            if self.status.running or busy:
                return False
            if kind == "full":
                self._pending_full = True
            else:
                self._pending_lift = True
            self._cancel.clear()
            self.status = JobStatus(
                kind=kind, phase="starting", message="starting", started_at=time.time()
            )
            self._cond.notify_all()
        self.emit("progress", -1)
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
    def emit(self, event: str, frame: int) -> None:
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
        self.emit("progress", -1)

    def _finish(self, phase: str, message: str) -> None:
        self._remove_partial()
        with self._cond:
            self.status.phase = phase
            self.status.message = message
            self.status.finished_at = time.time()
            self.history.append(JobStatus(**vars(self.status)))
            self._cond.notify_all()
        self.live.reload()
        self.emit("finished", -1)

    def check_cancelled(self) -> None:
        if self._cancel.is_set():
            raise Cancelled

    def _remove_partial(self) -> None:
        (self.session.folder / PARTIAL_FILE).unlink(missing_ok=True)

    def _lift_all(self) -> None:
        """Lift every annotated reference and estimate the bone lengths (saved on success only)."""
        self._set(phase="lift-all", done=0, total=0, message="")

        def progress(done: int, total: int) -> None:
            self.check_cancelled()
            self._set(done=int(done), total=int(total))

        self.lift_all_fn(self.session, workers=self.workers, quiet=True, progress=progress)
        self.live.reload()
        self.emit("lifted", -1)

    def _job(self, kind: str, corrections: dict[int, int]) -> None:
        if kind == "lift":
            self._lift_all()
            noise = self.session.click_noise_text()
            self._finish(
                "done",
                "done: references lifted, bone lengths estimated" + (f"; {noise}" if noise else ""),
            )
            return
        if kind == "full" and self.needs_lift():
            self._lift_all()
        frames = self._lift_corrections(corrections) if corrections else None
        parent = self.session.parent
        todo = np.flatnonzero(parent >= 0) if frames is None else frames[parent[frames] >= 0]
        self._propagate_refine(todo, frames)
        refined = "all frames refined" if frames is None else f"{len(frames)} refined"
        self._finish("done", f"done: {len(todo)} frame(s) propagated, {refined}")

    def _lift_corrections(self, corrections: dict[int, int]) -> np.ndarray:
        """Lift each corrected frame (at its journal entry or later); returns the frames to
        re-propagate (the corrected frames' descendants in the propagation's forests)."""
        from handanno_core.pipeline import frames_to_repropagate

        self._set(phase="lift", message=", ".join(map(str, sorted(corrections))))
        for frame, seq in sorted(corrections.items()):
            self.check_cancelled()
            joints, conf = self._lift(frame, seq)
            update_lifted(self.session, {frame: (joints, conf)})
            self.live.put(frame, joints, conf, Stage.LIFTED)
            self.emit("frame", frame)
        return frames_to_repropagate(self.session, sorted(corrections))

    def _propagate_refine(self, todo: np.ndarray, frames: np.ndarray | None) -> None:
        """Propagate ``todo`` (``frames`` None: every non-reference frame), then refine all
        (``frames`` given: only those, the others keep their refined result);
        propagation's init_mm and refinement's final_mm reach results.npz together in one atomic
        replace (session.staged_results), so a cancel, an error or a kill at any instant leaves
        results.npz exactly as it was before the job."""
        session = self.session
        self._set(
            phase="propagate", done=0, total=len(todo), frames=[int(f) for f in todo], message=""
        )
        on_result = _Checkpoint(self)

        def progress(done: int, total: int) -> None:
            self.check_cancelled()
            self._set(done=int(done), total=int(total))

        def refine_progress(iteration: int, energy: float) -> None:
            self.check_cancelled()
            self._set(done=int(iteration))

        with session.staged_results():
            if len(todo):
                self.propagate_fn(
                    session,
                    workers=self.workers,
                    frames=frames,
                    progress=progress,
                    on_result=on_result,
                    quiet=True,
                )
            self.check_cancelled()
            self._set(phase="refine", done=0, total=30, message="")
            if frames is None:
                final = self.refine_fn(session, progress=refine_progress)
            else:  # a correction moves only the frames it propagated again
                final = self.refine_fn(session, progress=refine_progress, frames=frames)
            self.check_cancelled()
            self._set(phase="saving")
            session.save_results(final_mm=final)
        self.live.put_all(final, Stage.REFINED)

    def _lift(self, frame: int, seq: int) -> tuple[np.ndarray, np.ndarray]:
        if self.lift_for is not None:
            joints = self.lift_for(frame, seq)
            if joints is not None:
                joints = np.asarray(joints, dtype=np.float64)
                return joints, np.ones(len(joints))
        depth = np.asarray(self.session.open_sequence().depth(frame), dtype=np.float32)
        try:
            joints, conf, _, _ = lift_for_session(self.session, frame, depth)
        except LiftUnavailable as exc:
            raise SessionError(f"frame {frame}: cannot lift: {exc}") from exc
        return joints, conf


class _Checkpoint:
    """Propagation's ``on_result``: each new skeleton goes to the live results at once, and what
    is computed so far is saved every ``checkpoint_every_s`` next to (never over) results.npz."""

    def __init__(self, runner: ReviewRunner):
        self.runner = runner
        shape = (runner.session.num_frames, runner.session.skeleton.num_joints)
        self.init_mm = np.full((*shape, 3), np.nan)
        self.confidence = np.full(shape, np.nan)
        self.last = time.monotonic()

    def __call__(self, frame: int, joints: np.ndarray, conf: np.ndarray) -> None:
        runner = self.runner
        runner.check_cancelled()
        self.init_mm[frame] = joints
        self.confidence[frame] = conf
        runner.live.put(
            int(frame),
            np.asarray(joints, dtype=np.float64),
            np.asarray(conf, dtype=np.float64),
            Stage.PROPAGATED,
        )
        runner.emit("frame", int(frame))
        if time.monotonic() - self.last >= runner.checkpoint_every_s:
            self.last = time.monotonic()
            atomic_save_npz(
                runner.session.folder / PARTIAL_FILE,
                {"init_mm": self.init_mm, "confidence": self.confidence},
            )
