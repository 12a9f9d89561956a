"""What changed, as topics (SLEAP's ``UpdateTopic``): the one place where a journal entry, a lift
result or a job event becomes an :class:`Update` that panels react to.

Panels never read ``entry.command["kind"]``; they check ``UpdateTopic.ANNOTATION in
update.topics`` and use ``update.frame`` / ``update.joints``. The :class:`EventBus` calls its
subscribers on the publishing thread (the session's listener runs under the session lock, so a
subscriber only records or enqueues; see :class:`app.ui.client_ui.ClientUI`).
"""

from __future__ import annotations

import threading
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum, auto
from typing import Any

from handanno_core.session import JournalEntry, parse_command


class UpdateTopic(Enum):
    ANNOTATION = auto()  # a frame's joints, visibility or depth order changed
    REFERENCES = auto()  # the reference selection changed (a review correction made one)
    REVIEW = auto()  # a frame's review status (accepted / flagged) changed
    LIFT = auto()  # the live lift worker lifted a frame
    RESULTS = auto()  # results.npz or the live results changed (lift all, propagation, import)
    JOB = auto()  # a background job's progress or phase changed
    RANKING = auto()  # the background review ranking of the live results is new


#: journal command kind -> topics it touches (a batch: the union of its commands')
_KIND_TOPICS: dict[str, frozenset[UpdateTopic]] = {
    "set_joint": frozenset({UpdateTopic.ANNOTATION}),
    "set_2d": frozenset({UpdateTopic.ANNOTATION}),
    "set_3d": frozenset({UpdateTopic.ANNOTATION}),
    "set_outside": frozenset({UpdateTopic.ANNOTATION}),
    "set_frame": frozenset({UpdateTopic.ANNOTATION}),
    "set_visible": frozenset({UpdateTopic.ANNOTATION}),
    "set_depth_order": frozenset({UpdateTopic.ANNOTATION}),
    "set_reference": frozenset({UpdateTopic.REFERENCES}),
    "set_review": frozenset({UpdateTopic.REVIEW}),
}


@dataclass(frozen=True)
class Update:
    """One change: its topics, the frame (-1: none or many), the joints whose placement changed,
    the journal client and seq of an edit (``""`` / -1 otherwise), and the payload of a lift
    (``lift``, a :class:`~app.control.jobs.LiftOutcome`) or a job event (``job``: ``"progress"``,
    ``"frame"``, ``"lifted"`` or ``"finished"``)."""

    topics: frozenset[UpdateTopic]
    frame: int = -1
    joints: tuple[int, ...] = ()
    client: str = ""
    seq: int = -1
    lift: Any = None
    job: str = ""


def _commands(entry: JournalEntry) -> list[dict[str, Any]]:
    if entry.command.get("kind") == "batch":
        return list(entry.command.get("commands", []))
    return [entry.command]


def entry_frame(entry: JournalEntry) -> int:
    """The frame a journal entry edits (-1 if none)."""
    try:
        return int(parse_command(entry.command).frame)
    except Exception:
        return -1


#: the joint fields that say where a joint is (its 2D or 3D point, or its mark outside the image)
_PLACEMENT_FIELDS = frozenset({"uv_px", "xyz_mm", "outside"})


def edited_joints(entry: JournalEntry, num_joints: int) -> tuple[int, ...]:
    """Joints whose placement a journal entry changes (all joints for whole-frame commands): a
    joint edit whose :meth:`changed_fields` include a placement field (an undo's ``set_joint``
    that restores only a flag moves nothing)."""
    out: set[int] = set()
    for c in _commands(entry):
        if c.get("kind") == "set_frame":
            out.update(range(num_joints))
            continue
        command = parse_command(c)
        changed = getattr(command, "changed_fields", None)
        if changed is not None and _PLACEMENT_FIELDS.intersection(changed()):
            out.add(int(command.joint))
    return tuple(sorted(out))


def entry_update(entry: JournalEntry, num_joints: int) -> Update:
    """The :class:`Update` of an acknowledged journal entry."""
    topics: set[UpdateTopic] = set()
    for c in _commands(entry):
        topics |= _KIND_TOPICS.get(str(c.get("kind")), frozenset())
    return Update(
        frozenset(topics),
        frame=entry_frame(entry),
        joints=edited_joints(entry, num_joints),
        client=entry.client,
        seq=entry.seq,
    )


def lift_update(outcome: Any) -> Update:
    return Update(frozenset({UpdateTopic.LIFT}), frame=int(outcome.frame), lift=outcome)


def job_update(event: str, frame: int = -1) -> Update:
    topics = {UpdateTopic.JOB}
    if event in ("frame", "lifted", "finished"):
        topics.add(UpdateTopic.RESULTS)
    return Update(frozenset(topics), frame=frame, job=event)


Subscriber = Callable[[Update], None]


class EventBus:
    """Publish :class:`Update`\\ s to subscribers (thread-safe; a failing subscriber is logged and
    never stops the others)."""

    def __init__(self) -> None:
        self._subscribers: list[Subscriber] = []
        self._lock = threading.Lock()

    def subscribe(self, fn: Subscriber) -> Callable[[], None]:
        """Add ``fn``; returns the function that removes it."""
        with self._lock:
            self._subscribers.append(fn)

        def unsubscribe() -> None:
            with self._lock:
                if fn in self._subscribers:
                    self._subscribers.remove(fn)

        return unsubscribe

    def publish(self, update: Update) -> None:
        with self._lock:
            subscribers = list(self._subscribers)
        for fn in subscribers:
            try:
                fn(update)
            except Exception:
                traceback.print_exc()
