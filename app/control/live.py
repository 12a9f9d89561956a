"""The skeletons the review panel shows, updated frame by frame while a job runs (no viser).

:class:`LiveResults` holds a copy of ``results.npz`` (``lifted_mm``, ``init_mm``, ``final_mm``
``(N, J, 3)`` mm, ``confidence`` ``(N, J)``) that the review runner overwrites frame by frame, and
the best joints of each frame with their :class:`~handanno_core.results.Stage`. It ranks frames
for review with the engine's evidence ranking (:func:`handanno_core.review.rank_priority`,
``"evidence"``) and scores them (:func:`handanno_core.review.session_scores`), both cached per
version. The crop cache is read through :func:`handanno_core.prefill.cached_crops` (never computed
from the UI).
"""

from __future__ import annotations

import threading

import numpy as np

from handanno_core.export import best_joints
from handanno_core.results import Stage
from handanno_core.review import FrameScores, rank_priority, session_scores
from handanno_core.session import Session

#: the results key each stage's joints are written to
_STAGE_KEY = {Stage.LIFTED: "lifted_mm", Stage.PROPAGATED: "init_mm", Stage.REFINED: "final_mm"}


class LiveResults:
    """Thread-safe live results; ``version`` grows with every change. ``joints_mm`` (N, J, 3) is
    the best stage per frame, ``stage`` (N,) int8 its :class:`Stage`."""

    def __init__(self, session: Session):
        self.session = session
        self._lock = threading.Lock()
        self.version = 0
        self._cache: dict[str, tuple[int, object]] = {}
        self._crops: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self.reload()

    def reload(self) -> None:
        results = {k: np.array(v, dtype=np.float64) for k, v in self.session.load_results().items()}
        joints, stage = best_joints(results)
        with self._lock:
            self.results = results
            self.joints_mm = joints
            self.stage = stage
            self.confidence = results["confidence"]
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
            self.results[_STAGE_KEY[Stage(stage)]][frame] = joints_mm
            self.joints_mm[frame] = joints_mm
            if confidence is not None:
                self.confidence[frame] = confidence
            self.stage[frame] = stage
            self.version += 1

    def put_all(self, joints_mm: np.ndarray, stage: int) -> None:
        ok = np.all(np.isfinite(joints_mm), axis=(1, 2))
        with self._lock:
            self.results[_STAGE_KEY[Stage(stage)]][ok] = joints_mm[ok]
            self.joints_mm[ok] = joints_mm[ok]
            self.stage[ok] = stage
            self.version += 1

    def frame(self, frame: int) -> tuple[np.ndarray, int]:
        with self._lock:
            return self.joints_mm[frame].copy(), int(self.stage[frame])

    def filled(self) -> int:
        with self._lock:
            return int((self.stage > 0).sum())

    def _crop_data(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        if self._crops is None:
            from handanno_core.prefill import cached_crops

            self._crops = cached_crops(self.session)
        return self._crops

    def _cached(self, name: str, compute) -> object:
        cached = self._cache.get(name)
        if cached is not None and cached[0] == self.version:
            return cached[1]
        with self._lock:
            version = self.version
            results = {k: v.copy() for k, v in self.results.items()}
            bones_mm = self.bone_lengths_mm
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

    def priority(self) -> np.ndarray:
        """``(N,)`` review priority, larger = show first, NaN = no skeleton: the engine's
        ``"evidence"`` ranking (:func:`~handanno_core.review.rank_priority`), cached per version."""

        def compute(results: dict[str, np.ndarray], _bones: np.ndarray | None) -> np.ndarray:
            return rank_priority("evidence", self.session, results, self._crop_data())

        return self._cached("priority", compute)  # type: ignore[return-value]
