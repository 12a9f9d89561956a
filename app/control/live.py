"""The skeletons the review panel shows, updated frame by frame while a job runs (no viser).

:class:`LiveResults` holds a copy of ``results.npz`` (``lifted_mm``, ``init_mm``, ``final_mm``
``(N, J, 3)`` mm, ``confidence`` ``(N, J)``, ``source`` ``(N,)``: the frame each propagated result
came from) that the review runner overwrites frame by frame, and
the best joints of each frame with their :class:`~handanno_core.results.Stage`. It ranks frames
for review with the engine's evidence ranking (:func:`handanno_core.review.rank_priority`,
``"evidence"``) and scores them (:func:`handanno_core.review.session_scores`), both cached per
version. The crop cache is read through :func:`handanno_core.prefill.cached_crops` (never computed
from the UI).

The ranking scales with the session (seconds for 76,000 frames), so the app never computes it on
a UI thread: :meth:`LiveResults.start_ranking` starts one background thread that re-ranks after
every change (coalesced: at most one ranking in flight, and while results keep changing, it rests
between rankings), and :meth:`LiveResults.ranking` answers with the
newest ranking at once. The costliest per-frame terms (:func:`handanno_core.review.unexplained_foreground`,
:func:`handanno_core.review.session_finger_ambiguity`) are recomputed only for frames whose joints
changed.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import numpy as np

from handanno_core.export import best_joints
from handanno_core.results import NO_SOURCE, Stage
from handanno_core.review import (
    FrameScores,
    rank_priority,
    session_finger_ambiguity,
    session_hand_models,
    session_scores,
    unexplained_foreground,
)
from handanno_core.session import Session

#: the results key each stage's joints are written to
_STAGE_KEY = {Stage.LIFTED: "lifted_mm", Stage.PROPAGATED: "init_mm", Stage.REFINED: "final_mm"}
#: how long :meth:`LiveResults.ranking` waits for the ranking of the current results before it
#: answers with the previous one (small sessions are ranked well within it: their answers are
#: always current)
RANK_WAIT_S = 0.15
#: the ranking thread rests as long as its last ranking took, at most this long, before it ranks
#: changed results again (while a job changes results, ranking takes at most about half a core;
#: while the finger ambiguity of a large session fills in, up to 0.8 of one)
RANK_REST_S = 2.0
#: frames whose finger ambiguity one ranking computes at most (its cost per frame bounds how long
#: a change made meanwhile waits for the next ranking: README, stop 48); 0: the term is off
AMBIGUITY_FRAMES_PER_RANKING = 300


class LiveResults:
    """Thread-safe live results; ``version`` grows with every change. ``joints_mm`` (N, J, 3) is
    the best stage per frame, ``stage`` (N,) int8 its :class:`Stage`. ``on_ranked``: called (on
    the ranking thread) with the results version of every new background ranking."""

    def __init__(self, session: Session, on_ranked: Callable[[int], None] | None = None):
        self.session = session
        self._lock = threading.Lock()
        self.version = 0
        self._cache: dict[str, tuple[int, object]] = {}
        self._crops: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        # the background ranking: (results version, priority (N,)) of the newest one
        self.on_ranked = on_ranked
        self._ranked: tuple[int, np.ndarray] | None = None
        self._rank_cv = threading.Condition()
        self._rank_thread: threading.Thread | None = None
        self._rank_stop = False
        #: seconds the last ranking took (also how long the thread rests while results change)
        self.rank_seconds = 0.0
        # unexplained_foreground and session_finger_ambiguity per frame, and the joints they
        # were computed for
        self._ux: np.ndarray | None = None
        self._amb: np.ndarray | None = None
        self._amb_stale = np.zeros(0, dtype=bool)  # frames whose ambiguity is still to compute
        self._models = None  # (key, session_hand_models) of the references last ranked with
        self._ux_joints: np.ndarray | None = None
        self._ux_lock = threading.Lock()
        self.reload()

    def reload(self) -> None:
        results = {k: np.array(v) for k, v in self.session.load_results().items()}
        joints, stage = best_joints(results)
        with self._lock:
            self.results = results
            self.joints_mm = joints
            self.stage = stage
            self.confidence = results["confidence"]
            # (B,), or (N, B) with several hands: each frame its hand's
            self.bone_lengths_mm = self.session.frame_bone_lengths()
            self.version += 1
            # propagation may have placed crops again (pipeline.recrop_from_references)
            self._crops = None
        self._changed()

    def put(
        self, frame: int, joints_mm: np.ndarray, confidence: np.ndarray | None, stage: int
    ) -> None:
        with self._lock:
            self.results[_STAGE_KEY[Stage(stage)]][frame] = joints_mm
            if stage == Stage.PROPAGATED:  # its kept source is known once the run is saved
                self.results["source"][frame] = NO_SOURCE
            self.joints_mm[frame] = joints_mm
            if confidence is not None:
                self.confidence[frame] = confidence
            self.stage[frame] = stage
            self.version += 1
        self._changed()

    def put_all(self, joints_mm: np.ndarray, stage: int) -> None:
        ok = np.all(np.isfinite(joints_mm), axis=(1, 2))
        with self._lock:
            self.results[_STAGE_KEY[Stage(stage)]][ok] = joints_mm[ok]
            self.joints_mm[ok] = joints_mm[ok]
            self.stage[ok] = stage
            self.version += 1
        self._changed()

    def frame(self, frame: int) -> tuple[np.ndarray, int]:
        with self._lock:
            return self.joints_mm[frame].copy(), int(self.stage[frame])

    def source(self, frame: int) -> int:
        """The frame ``frame``'s propagated result came from (``results.npz`` ``source``, the
        candidate chain propagation kept), :data:`~handanno_core.results.NO_SOURCE` for a
        reference, a frame not propagated, or one re-propagated by a run still going."""
        with self._lock:
            return int(self.results["source"][frame])

    def filled(self) -> int:
        with self._lock:
            return int((self.stage > 0).sum())

    def _crop_data(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        if self._crops is None:
            from handanno_core.prefill import cached_crops

            self._crops = cached_crops(self.session)
        return self._crops

    def _snapshot(self) -> tuple[int, dict[str, np.ndarray], np.ndarray | None]:
        with self._lock:
            return (
                self.version,
                {k: v.copy() for k, v in self.results.items()},
                self.bone_lengths_mm,
            )

    def _cached(self, name: str, compute) -> object:
        cached = self._cache.get(name)
        if cached is not None and cached[0] == self.version:
            return cached[1]
        version, results, bones_mm = self._snapshot()
        value = compute(results, bones_mm)
        self._cache[name] = (version, value)
        return value

    def scores(self) -> FrameScores:
        """:func:`~handanno_core.review.session_scores` of the current skeletons (cached per
        version; the depth term only when the session's crops are cached on disk)."""

        def compute(results: dict[str, np.ndarray], bones_mm: np.ndarray | None) -> FrameScores:
            joints, _ = best_joints(results)
            return session_scores(
                self.session,
                joints,
                results["confidence"],
                self._crop_data(),
                bone_lengths_mm=bones_mm,
            )

        return self._cached("scores", compute)  # type: ignore[return-value]

    # ------------------------------------------------------------------ the review ranking
    def priority(self) -> np.ndarray:
        """``(N,)`` review priority of the current results, larger = show first, NaN = no
        skeleton: the engine's ``"evidence"`` ranking (:func:`~handanno_core.review.rank_priority`),
        cached per version. Computed on the calling thread when not cached: the app uses
        :meth:`ranking` instead."""
        return self._cached("priority", self._rank)  # type: ignore[return-value]

    def _rank(self, results: dict[str, np.ndarray], _bones: np.ndarray | None) -> np.ndarray:
        """The evidence ranking of ``results``, its two costly per-frame terms (unexplained
        foreground, finger ambiguity) recomputed only for frames whose shown joints changed since
        the last ranking (a new reference changes the personalized model a little; the frames it
        did not move keep their ambiguity until they change)."""
        crop_data = self._crop_data()
        unexplained = ambiguity = None
        if crop_data is not None:
            crops, _, boxes = crop_data
            joints, _ = best_joints(results)
            with self._ux_lock:  # one ranking at a time updates the per-frame terms
                if self._ux is None or self._amb is None or self._ux_joints is None:
                    todo = np.arange(len(joints))
                    self._ux = np.full(len(joints), np.nan)
                    self._amb = np.full(len(joints), np.nan)
                    self._amb_stale = np.full(len(joints), AMBIGUITY_FRAMES_PER_RANKING > 0)
                else:
                    old = self._ux_joints
                    same = (joints == old) | (np.isnan(joints) & np.isnan(old))
                    todo = np.flatnonzero(~np.all(same, axis=(1, 2)))
                if todo.size:
                    fresh = unexplained_foreground(
                        joints, crops, boxes, self.session.camera, self.session.skeleton.bones,
                        frames=todo,
                    )  # fmt: skip
                    self._ux[todo] = fresh[todo]
                    self._amb_stale[todo] = AMBIGUITY_FRAMES_PER_RANKING > 0
                # the ambiguity costs tens of ms per frame: at most AMBIGUITY_FRAMES_PER_RANKING
                # per ranking, changed frames first, and none in a large session's first ranking,
                # so that it comes as soon as before; the term fills in over the next rankings
                # (NaN: no evidence yet)
                stale = np.flatnonzero(self._amb_stale)
                stale = np.concatenate([np.intersect1d(stale, todo), np.setdiff1d(stale, todo)])
                first = self._ranked is None and stale.size > AMBIGUITY_FRAMES_PER_RANKING
                part = stale[: 0 if first else AMBIGUITY_FRAMES_PER_RANKING]
                models = self._hand_models(joints, crop_data) if part.size else None
                if models is not None:  # else no references, bones or finger layout: NaN
                    amb = session_finger_ambiguity(
                        self.session, joints, crop_data, frames=part, models=models
                    )
                    self._amb[part] = amb[part]
                self._amb_stale[part] = False
                self._ux_joints = joints
                unexplained, ambiguity = self._ux.copy(), self._amb.copy()
        return rank_priority(
            "evidence", self.session, results, crop_data, unexplained=unexplained,
            ambiguity=ambiguity,
        )  # fmt: skip

    def _hand_models(self, joints: np.ndarray, crop_data):
        """:func:`~handanno_core.review.session_hand_models` of ``joints``, kept while the
        references, their joints and the bone lengths stay the same (personalizing from thousands of references
        takes tens of seconds; a ranking that fills in the ambiguity would redo it every time)."""
        refs = np.asarray(self.session.reference_frames, dtype=np.int64)
        bones = self.session.model.bone_lengths_mm
        key = (
            refs.tobytes(),
            joints[refs].tobytes(),
            np.asarray([] if bones is None else bones, dtype=np.float64).tobytes(),
        )
        if self._models is None or self._models[0] != key:
            self._models = (key, session_hand_models(self.session, joints, crop_data))
        return self._models[1]

    def start_ranking(self) -> None:
        """Start the background ranking thread (it ranks the current results at once, then again
        after every change). Idempotent."""
        with self._rank_cv:
            if self._rank_thread is not None or self._rank_stop:
                return
            self._rank_thread = threading.Thread(
                target=self._rank_loop, name="handanno-ranking", daemon=True
            )
            self._rank_thread.start()

    def stop_ranking(self, timeout: float = 30.0) -> None:
        with self._rank_cv:
            self._rank_stop = True
            self._rank_cv.notify_all()
            thread = self._rank_thread
        if thread is not None:
            thread.join(timeout)

    def _changed(self) -> None:
        with self._rank_cv:
            self._rank_cv.notify_all()

    def _rank_loop(self) -> None:
        import traceback

        while True:
            with self._rank_cv:
                while not self._rank_stop and (
                    self._ranked is not None
                    and self._ranked[0] == self.version
                    and not self._amb_stale.any()
                ):
                    self._rank_cv.wait()
                if self._rank_stop:
                    return
            try:
                t0 = time.monotonic()
                version, results, bones = self._snapshot()
                priority = self._rank(results, bones)
                self.rank_seconds = time.monotonic() - t0
            except Exception:  # a failed ranking keeps the previous one; retry after a pause
                traceback.print_exc()
                time.sleep(5.0)
                continue
            with self._rank_cv:
                self._ranked = (version, priority)
                self._cache["priority"] = (version, priority)
                self._rank_cv.notify_all()
            if self.on_ranked is not None:
                try:
                    self.on_ranked(version)
                except Exception:
                    traceback.print_exc()
            # results still changing (a job): rest as long as the ranking took, at most RANK_REST_S
            rest_until = time.monotonic() + min(self.rank_seconds, RANK_REST_S)
            with self._rank_cv:
                while not self._rank_stop and time.monotonic() < rest_until:
                    self._rank_cv.wait(rest_until - time.monotonic())

    def ranking(self, wait_s: float | None = RANK_WAIT_S) -> np.ndarray | None:
        """The newest review priority ``(N,)`` (as :meth:`priority`) without ranking on this
        thread: the one of the current results if the background thread has it within ``wait_s``
        seconds (None: wait as long as it takes), else the previous one; None while none has been
        computed yet. Starts the background thread if needed."""
        self.start_ranking()
        deadline = None if wait_s is None else time.monotonic() + wait_s
        with self._rank_cv:
            while self._ranked is None or self._ranked[0] != self.version:
                left = None if deadline is None else deadline - time.monotonic()
                if (left is not None and left <= 0) or self._rank_stop:
                    break
                self._rank_cv.wait(left)
            return None if self._ranked is None else self._ranked[1]

    def ranked_version(self) -> int:
        """The results version of the newest ranking (-1 before the first)."""
        ranked = self._ranked
        return -1 if ranked is None else ranked[0]
