"""What one reviewer is doing, without viser: the shown frame, the review walk ("next worst"),
and every review action as a session command (SLEAP style: testable without a browser).

Edits return the acknowledged :class:`~handanno_core.session.JournalEntry` and raise
:class:`~handanno_core.session.SessionError` (not saved) or ``ValueError`` (refused); the review
panel turns those into notifications.

The walk: :meth:`ReviewState.next_worst` shows frames by decreasing review priority (the engine's
``"evidence"`` ranking, the newest one :meth:`LiveResults.ranking` has: ranked in the background,
so a step costs O(N) numpy and never a ranking), never a reference, a frame with a review
status (accepted or flagged) or a frame the walk already showed, and no frame within
:data:`NEIGHBOUR_RADIUS` frames of one it showed while any other frame is left.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from handanno_core.review import correction_command
from handanno_core.session import Batch, Command, JournalEntry, Session, SessionError, SetReview

from .jobs import ReviewRunner
from .live import LiveResults

#: frames this close (in time) to a frame the walk showed come last (one bad stretch should not
#: fill the walk)
NEIGHBOUR_RADIUS = 2
#: export format label -> (export_bytes format, file extension)
EXPORT_FORMATS = {"JSON": ("json", "json"), "NPZ": ("npz", "npz"), "MSRA": ("msra", "txt")}
#: what a frame's shown joints are, by their :class:`~handanno_core.results.Stage`
STAGE_TEXT = {0: "not computed yet", 1: "lifted", 2: "propagated", 3: "refined"}


def frame_text(frame: int, stage: int, is_reference: bool, source: int, review: str | None) -> str:
    """The review panel's line about ``frame``: what its shown joints are (reference, or their
    :class:`~handanno_core.results.Stage`), the frame its propagated result was propagated from
    (``source``: ``results.npz``'s kept candidate chain, not necessarily the selection's parent;
    omitted when < 0) and its review status, e.g. ``**Review frame 15** (refined, propagated
    from frame 20, flagged)``."""
    bits = ["reference" if is_reference else STAGE_TEXT[int(stage)]]
    if not is_reference and source >= 0 and stage >= 2:
        bits.append(f"propagated from frame {int(source)}")
    if review:
        bits.append(review)
    return f"**Review frame {frame}** ({', '.join(bits)})"


class ReviewState:
    """One reviewer's state; see the module docstring."""

    def __init__(self, session: Session, live: LiveResults, runner: ReviewRunner, client: str):
        self.session = session
        self.live = live
        self.runner = runner
        self.client = client
        self.frame = 0
        #: frames the "next worst" walk has shown, in order
        self.walked: list[int] = []

    # ------------------------------------------------------------------ navigation
    def go_to(self, frame: int) -> int:
        self.frame = int(np.clip(frame, 0, self.session.num_frames - 1))
        return self.frame

    def step(self, step: int) -> int:
        return self.go_to(self.frame + step)

    def next_worst(self) -> int | None:
        """Go to the next frame of the walk (see the module docstring); None when none is left."""
        ranked = self.live.ranking()
        if ranked is None:  # nothing ranked yet (a session just opened): wait for the first
            ranked = self.live.ranking(wait_s=None)
        priority = np.asarray(ranked, dtype=np.float64)
        n = len(priority)
        walked = np.asarray(self.walked, dtype=np.int64)
        done = np.concatenate(
            [
                np.fromiter(map(int, self.session.model.review), dtype=np.int64),
                self.session.reference_frames,
                walked,
            ]
        )
        ok = np.isfinite(priority)
        ok[done[(done >= 0) & (done < n)]] = False
        near = np.zeros(n, dtype=bool)
        around = (walked[:, None] + np.arange(-NEIGHBOUR_RADIUS, NEIGHBOUR_RADIUS + 1)).ravel()
        near[around[(around >= 0) & (around < n)]] = True
        cand = np.flatnonzero(ok & ~near)
        if cand.size == 0:
            cand = np.flatnonzero(ok)
        if cand.size == 0:
            return None
        frame = int(cand[np.argmax(priority[cand])])  # the first of equals: the earliest frame
        self.walked.append(frame)
        return self.go_to(frame)

    # ------------------------------------------------------------------ edits
    def set_review(self, status: str | None) -> JournalEntry:
        return self.session.execute(SetReview(frame=self.frame, status=status), self.client)

    def accept(self) -> JournalEntry:
        """Accept the shown frame, then go on to the next frame of the walk."""
        entry = self.set_review("accepted")
        self.next_worst()
        return entry

    def flag(self) -> JournalEntry:
        return self.set_review("flagged")

    def move_joint(
        self, joint: int, xyz_mm: np.ndarray, shown_mm: np.ndarray, depth_mm: np.ndarray | None
    ) -> JournalEntry:
        """Review edit: move ``joint`` of the shown frame to ``xyz_mm`` (mm). On a propagated frame
        it is a correction (:func:`~handanno_core.review.correction_command`: the frame becomes a
        reference seeded from ``shown_mm`` (J, 3)); a flagged frame loses its flag in the same
        journal entry (one undo step). The runner then re-propagates its descendants."""
        if not np.all(np.isfinite(shown_mm)):
            raise ValueError("this frame has no skeleton yet")
        frame = self.frame
        with self.session.lock:  # decide "seed or not" and execute atomically (two annotators)
            command, _ = correction_command(self.session, frame, joint, xyz_mm, shown_mm, depth_mm)
            if self.session.model.review.get(str(frame)) == "flagged":
                command = _with_unflag(command, frame)
            entry = self.session.execute(command, self.client)
        self.runner.request_correction(frame, entry.seq)
        return entry

    # ------------------------------------------------------------------ import / export
    def export_bytes(self, label: str) -> tuple[str, bytes]:
        """``(download file name, bytes)`` of the session's export in format ``label``."""
        from handanno_core.export import export_bytes

        fmt, ext = EXPORT_FORMATS[label]
        name = self.session.model.name
        return (f"{name}-{fmt}.{ext}" if fmt == "msra" else f"{name}.{ext}"), export_bytes(
            self.session, fmt
        )

    def import_upload(self, name: str, content: bytes) -> int:
        """Import an uploaded JSON export (written to a temporary file; the upload's name is never
        used as a path); returns the number of frames imported. Errors name the upload."""
        from handanno_core.export import import_json

        with tempfile.TemporaryDirectory(prefix="handanno-import-") as tmp:
            path = Path(tmp) / "upload.json"
            path.write_bytes(content)
            try:
                count = import_json(self.session, path, client=self.client)
            except (SessionError, ValueError, KeyError) as exc:
                raise type(exc)(str(exc).replace(str(path), name)) from exc
        self.live.reload()
        return count


def _with_unflag(command: Command, frame: int) -> Batch:
    """``command`` and "clear the review flag of ``frame``" as one Batch."""
    unflag = SetReview(frame=frame, status=None).model_dump()
    if isinstance(command, Batch):
        return Batch(commands=[*command.commands, unflag])
    return Batch(commands=[command.model_dump(), unflag])
