"""The application layer's context (SLEAP's ``CommandContext``), no viser: one per served session.

:class:`AppContext` owns the :class:`~handanno_core.session.Session`, the
:class:`~app.control.frames.FrameStore`, the live :class:`~app.control.jobs.LiftWorker`, the
review :class:`~app.control.live.LiveResults` and :class:`~app.control.jobs.ReviewRunner`, the
:class:`~app.control.events.EventBus`, and the journal names of the connected browsers. It turns
every acknowledged journal entry, lift result and job event into an
:class:`~app.control.events.Update` on the bus (job progress coalesced to at most one update per
``tick_s``). Options of the runner (tests slow propagation down, shorten the debounce) are
constructor arguments.
"""

from __future__ import annotations

import threading
import time
import traceback
from typing import Any

import numpy as np

from handanno_core.results import Stage
from handanno_core.session import JournalEntry, Session
from handanno_core.synth import template_hand

from .annotate import AnnotateState
from .events import EventBus, Update, UpdateTopic, entry_update, job_update, lift_update
from .frames import FrameStore
from .jobs import LiftFunction, LiftOutcome, LiftWorker, ReviewRunner
from .live import LiveResults
from .review import ReviewState


class AppContext:
    """See the module docstring. ``review_options`` go to :class:`ReviewRunner` (e.g.
    ``propagate_fn``, ``debounce_s``, ``workers``); ``lift_fn`` to the :class:`LiftWorker`."""

    def __init__(
        self,
        session: Session,
        *,
        lift_fn: LiftFunction | None = None,
        review_options: dict[str, Any] | None = None,
        tick_s: float = 0.3,
    ):
        self.session = session
        self.frames = FrameStore(session)
        self.bus = EventBus()
        self.worker = LiftWorker(
            session,
            self.frames,
            lift_fn=lift_fn,
            on_result=self._on_lift,
            initial_guess=self.prefill,
            guess_model=self.guess_model,
        )
        self.live = LiveResults(session, on_ranked=self._on_ranked)
        self.live.start_ranking()  # ranked in the background from the start (seconds at 76k frames)
        options: dict[str, Any] = {"lift_for": self._lift_for}
        options.update(review_options or {})
        self.runner = ReviewRunner(session, self.live, **options)
        self.runner.listeners.append(self._on_job)
        self.tick_s = tick_s
        self._stop = threading.Event()
        self._ticker = threading.Thread(target=self._tick, name="handanno-ticker", daemon=True)
        self.worker.start()
        self._ticker.start()
        self._unsubscribe = session.subscribe(self._on_entry)

    # ------------------------------------------------------------------ per-client states
    def annotate_state(self, client: str) -> AnnotateState:
        return AnnotateState(self.session, client=client)

    def review_state(self, client: str) -> ReviewState:
        return ReviewState(self.session, self.live, self.runner, client)

    def guess_model(self, frame: int) -> dict:
        """The hand model and ``frame``'s points the live refits fit its guesses with
        (:func:`handanno_core.prefill.guess_model`; ``{}`` before "Lift all" has two lifted
        references, or without the crop cache)."""
        from handanno_core.prefill import guess_model

        return guess_model(self.session, frame)

    def prefill(self, frame: int) -> np.ndarray | None:
        """``(J, 3)`` mm first guess of ``frame``'s joints, always hand-shaped:
        :func:`handanno_core.prefill.prefill_reference` (the frame's own results, else one
        propagation step from the nearest frame with joints, fitted to the frame's own depth with
        the hand model personalized from the lifted references once there are two,
        :func:`handanno_core.prefill.session_hand_model`), else, when nothing in the session
        has joints yet, :func:`handanno_core.synth.template_hand` at the frame's hand centre.
        None where neither exists. Never raises: a failed pre-fill only means no first guess."""
        from handanno_core.prefill import prefill_reference, session_hand_model

        try:
            results = self.session.load_results()
            try:
                model = session_hand_model(self.session, frame, results)
            except Exception:  # no model fit: the flow-only pre-fill
                traceback.print_exc()
                model = False
            joints = prefill_reference(self.session, frame, results, hand_model=model)
            if joints is None:
                data = self.frames.get(frame)
                if data.depth is not None:
                    joints = template_hand(self.session.skeleton, data.geometry.centre_mm)
        except Exception:
            traceback.print_exc()
            return None
        if joints is None or not np.all(np.isfinite(joints)):
            return None
        return np.asarray(joints, dtype=np.float64)

    # ------------------------------------------------------------------ events
    def _on_entry(self, entry: JournalEntry) -> None:
        """Every acknowledged edit (called by the session, under its lock): re-lift, publish."""
        update = entry_update(entry, self.session.skeleton.num_joints)
        if update.frame >= 0 and UpdateTopic.ANNOTATION in update.topics:
            self.worker.submit(update.frame)
        self.bus.publish(update)

    def _on_lift(self, frame: int, outcome: LiftOutcome) -> None:
        """The lift worker lifted a frame: a review-made reference's new skeleton goes to the
        live results too."""
        if outcome.joints_mm is not None and frame in set(self.session.model.corrections):
            self.live.put(frame, outcome.joints_mm, None, Stage.LIFTED)
        self.bus.publish(lift_update(outcome))

    def _on_job(self, event: str, runner: ReviewRunner, frame: int) -> None:
        if event == "lifted":  # "lift all" replaced the references' lifted joints on disk
            self.worker.forget(self.session.reference_frames)
        if event != "progress":
            self.bus.publish(job_update(event, frame))

    def _on_ranked(self, version: int) -> None:
        self.bus.publish(Update(frozenset({UpdateTopic.RANKING})))

    def _tick(self) -> None:
        """Publish job progress at most every ``tick_s`` (when it changed)."""
        shown: tuple = ()
        while not self._stop.wait(self.tick_s):
            st = self.runner.status
            now = (st.phase, st.done, st.total, st.message, self.live.version)
            if now != shown:
                shown = now
                self.bus.publish(job_update("progress"))

    def _lift_for(self, frame: int, seq: int, timeout_s: float = 300.0) -> np.ndarray | None:
        """Wait for the lift worker to lift ``frame`` at journal entry ``seq`` or later."""
        if not self.worker.available:
            return None
        self.worker.submit(frame)
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            out = self.worker.latest.get(frame)
            if out is not None and out.journal_seq >= seq:
                return out.joints_mm
            time.sleep(0.05)
        return None

    # ------------------------------------------------------------------ lifetime
    def stop(self) -> None:
        """Stop the jobs (the runner before the session closes), then close the session."""
        self._unsubscribe()
        self._stop.set()
        self.runner.stop()
        self.worker.stop()
        self.live.stop_ranking()
        self.session.close()
