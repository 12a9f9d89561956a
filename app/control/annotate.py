"""What one annotator is doing, without viser: current frame, selected joint, click mode, and
every annotation action as a session command (SLEAP style: testable without a browser).

Each action that edits returns the acknowledged :class:`~handanno_core.session.JournalEntry`
(journaled and fsynced by ``Session.execute`` before it returns), or None if there was nothing
to do. Navigation walks the reference frames (all frames if the session has no selection yet).
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from handanno_core.annotation import FrameAnnotation
from handanno_core.camera import CameraIntrinsics
from handanno_core.session import (
    Batch,
    JournalEntry,
    Session,
    SetDepthOrder,
    SetJoint2D,
    SetJoint3D,
    SetOutside,
    SetVisibility,
)

from .events import entry_frame
from .geometry import surface_under

ClickMode = Literal["2d", "3d"]
#: the order "D" cycles depth order through.
DEPTH_ORDER_CYCLE = {0: -1, -1: 1, 1: 0}
DEPTH_ORDER_TEXT = {-1: "closer", 0: "unknown", 1: "farther"}


class AnnotateState:
    def __init__(self, session: Session, client: str):
        self.session = session
        self.client = client
        refs = [int(f) for f in session.reference_frames]
        self.frames: list[int] = refs if refs else list(range(session.num_frames))
        self.has_selection = bool(refs)
        self.index = self._first_unfinished()
        self.joint = self.first_unplaced_joint()
        self.click_mode: ClickMode = "2d"

    # ------------------------------------------------------------------ navigation
    @property
    def frame(self) -> int:
        return self.frames[self.index]

    @property
    def num_joints(self) -> int:
        return self.session.skeleton.num_joints

    def _first_unfinished(self) -> int:
        for i, f in enumerate(self.frames):
            if not self.session.is_annotated(f):
                return i
        return 0

    def go_to_index(self, index: int) -> int:
        """Select the ``index``-th navigable frame (clamped); returns the frame."""
        self.index = int(np.clip(index, 0, len(self.frames) - 1))
        self.joint = self.first_unplaced_joint()
        return self.frame

    def next_frame(self) -> int:
        return self.go_to_index(self.index + 1)

    def prev_frame(self) -> int:
        return self.go_to_index(self.index - 1)

    def select_joint(self, joint: int) -> None:
        self.joint = int(joint) % self.num_joints

    def annotation(self) -> FrameAnnotation:
        return self.session.annotation(self.frame) or FrameAnnotation.empty(self.num_joints)

    def first_unplaced_joint(self) -> int:
        placed = self.annotation().complete
        missing = np.flatnonzero(~placed)
        return int(missing[0]) if missing.size else 0

    def advance_joint(self) -> int:
        """After placing: select the next unplaced joint after the current one (wrapping), or
        simply the next joint when all are placed (or marked outside the image)."""
        placed = self.annotation().complete
        j = self.num_joints
        for step in range(1, j + 1):
            k = (self.joint + step) % j
            if not placed[k]:
                self.joint = k
                return k
        self.joint = (self.joint + 1) % j
        return self.joint

    # ------------------------------------------------------------------ edits
    def _execute(self, command) -> JournalEntry:
        return self.session.execute(command, client=self.client)

    def place_2d(
        self, uv_px: np.ndarray, joint: int | None = None, advance: bool = True
    ) -> JournalEntry:
        """Set the (selected) joint's 2D position; the next unplaced joint becomes selected.

        A joint placed in 3D before (by hand, or seeded from the shown skeleton by a review
        correction) loses that 3D position in the same journal entry: the click says where the
        joint is, and a 3D position elsewhere would pull the lift back to where it was."""
        j = self.joint if joint is None else int(joint)
        uv = self.session.camera.onto_image(uv_px)
        click = SetJoint2D(
            frame=self.frame, joint=j, uv_px=(round(float(uv[0]), 2), round(float(uv[1]), 2))
        )
        if self.annotation().has_3d[j]:
            clear = SetJoint3D(frame=self.frame, joint=j, xyz_mm=None)
            entry = self._execute(Batch(commands=[clear.model_dump(), click.model_dump()]))
        else:
            entry = self._execute(click)
        self.joint = j
        if advance:
            self.advance_joint()
        return entry

    def place_3d(
        self, xyz_mm: np.ndarray, joint: int | None = None, advance: bool = True
    ) -> JournalEntry:
        """Place the (selected) joint in 3D (mm, camera frame)."""
        j = self.joint if joint is None else int(joint)
        xyz = tuple(round(float(x), 2) for x in np.asarray(xyz_mm, dtype=np.float64))
        entry = self._execute(SetJoint3D(frame=self.frame, joint=j, xyz_mm=xyz))  # type: ignore[arg-type]
        self.joint = j
        if advance:
            self.advance_joint()
        return entry

    def accept_guesses(self, guesses_mm: np.ndarray) -> JournalEntry | None:
        """Place every joint not placed yet at the 2D projection of its guess ``guesses_mm``
        ``(J, 3)`` mm (NaN rows = no guess; guesses drawn off the image and joints marked outside
        it are skipped), flagged as
        accepted (the lift weighs them below clicks; a later click or drag clears the flag): ONE
        journal entry (a Batch), undone in one step. None if there is nothing to place."""
        cam = self.session.camera
        ann = self.annotation()
        guesses = np.asarray(guesses_mm, dtype=np.float64)
        ok = ~ann.complete & np.all(np.isfinite(guesses), axis=1) & (guesses[:, 2] > 0)
        uv = cam.project(np.where(ok[:, None], guesses, [[0.0, 0.0, 1.0]]))
        ok &= cam.on_image(uv)
        if not ok.any():
            return None
        commands = [
            SetJoint2D(
                frame=self.frame,
                joint=int(j),
                uv_px=(round(float(uv[j, 0]), 2), round(float(uv[j, 1]), 2)),
                accepted=True,
            ).model_dump()
            for j in np.flatnonzero(ok)
        ]
        entry = self._execute(Batch(commands=commands))
        self.joint = self.first_unplaced_joint()
        return entry

    def clear_joint(self) -> JournalEntry | None:
        ann = self.annotation()
        j = self.joint
        if ann.has_3d[j]:
            return self._execute(SetJoint3D(frame=self.frame, joint=j, xyz_mm=None))
        if ann.has_2d[j]:
            return self._execute(SetJoint2D(frame=self.frame, joint=j, uv_px=None))
        if ann.outside[j]:
            return self._execute(SetOutside(frame=self.frame, joint=j, outside=False))
        return None

    def toggle_outside(self) -> JournalEntry:
        """Mark the selected joint outside the image (clearing its placement; the next unplaced
        joint becomes selected) or, if it is marked, take the mark away."""
        j = self.joint
        outside = not bool(self.annotation().outside[j])
        entry = self._execute(SetOutside(frame=self.frame, joint=j, outside=outside))
        if outside:
            self.advance_joint()
        return entry

    def toggle_visibility(self) -> JournalEntry:
        visible = bool(self.annotation().visible[self.joint])
        return self._execute(SetVisibility(frame=self.frame, joint=self.joint, visible=not visible))

    def cycle_depth_order(self) -> JournalEntry | None:
        if self.session.skeleton.parent_array[self.joint] < 0:
            return None  # the root has no parent to compare with
        order = int(self.annotation().depth_order[self.joint])
        return self._execute(
            SetDepthOrder(frame=self.frame, joint=self.joint, order=DEPTH_ORDER_CYCLE[order])
        )

    def undo(self) -> JournalEntry | None:
        """Undo this annotator's last edit; an undone edit of one joint on this frame selects
        that joint again (so the next click re-places it)."""
        entry = self.session.undo(self.client)
        if entry is not None and entry_frame(entry) == self.frame:
            joint = entry.command.get("joint")
            if joint is not None:
                self.joint = int(joint)
        return entry

    def redo(self) -> JournalEntry | None:
        return self.session.redo(self.client)

    def toggle_click_mode(self) -> ClickMode:
        self.click_mode = "3d" if self.click_mode == "2d" else "2d"
        return self.click_mode

    # ------------------------------------------------------------------ text for the panel
    def progress_text(self) -> str:
        done, total = self.session.progress()
        if not self.has_selection:
            return "No reference selection yet (run `handanno select`): browsing all frames."
        return f"{done} of {total} reference frames annotated"

    def joint_text(self) -> tuple[str, str]:
        """(visibility text, depth-order text) of the selected joint."""
        ann = self.annotation()
        if ann.outside[self.joint]:
            return "outside the image", "n/a (outside the image)"
        vis = "visible" if ann.visible[self.joint] else "occluded"
        if self.session.skeleton.parent_array[self.joint] < 0:
            return vis, "n/a (root)"
        return vis, DEPTH_ORDER_TEXT[int(ann.depth_order[self.joint])]


def display_joints(
    annotation: FrameAnnotation,
    camera: CameraIntrinsics,
    depth: np.ndarray | None,
    centre_mm: np.ndarray,
    *,
    lifted_mm: np.ndarray | None = None,
    stale: list[int] | tuple[int, ...] = (),
    prefill_mm: np.ndarray | None = None,
) -> np.ndarray:
    """(J, 3) mm where the annotate panel draws each joint; NaN = unknown.

    The lifted joints ``lifted_mm`` (J, 3) (joints in ``stale``, edited after that lift, follow
    their annotation at once: instant feedback until the next lift), else the pre-fill
    ``prefill_mm`` for joints not placed; then for every joint still unknown its placed 3D point,
    else its 2D point on the depth surface ``depth`` (H, W) mm (at the hand centre's depth
    ``centre_mm[2]`` where the depth has a hole). A joint marked outside the image is drawn only
    where its position projects off the image: the annotator said it is not on it.
    """
    ann = annotation
    out = np.full((len(ann.annotated), 3), np.nan)
    if lifted_mm is not None:
        out[:] = lifted_mm
        stale_placed = [j for j in stale if ann.annotated[j]]
        out[stale_placed] = np.nan
    elif prefill_mm is not None:  # before the first lift: the pre-filled pose
        out[:] = prefill_mm
        out[ann.annotated] = np.nan  # placed joints are drawn where they were placed
    missing = ~np.all(np.isfinite(out), axis=1)
    out[missing & ann.has_3d] = ann.xyz_mm[missing & ann.has_3d]
    only2d = missing & ~ann.has_3d & ann.has_2d
    if only2d.any():
        uv = ann.uv_px[only2d]
        z = np.full(len(uv), float(centre_mm[2]))
        if depth is not None:
            d = surface_under(depth, uv)
            z = np.where(np.isfinite(d), d, z)
        out[only2d] = camera.backproject(uv, z)
    marked = ann.outside & np.all(np.isfinite(out), axis=1) & (out[:, 2] > 0)
    if marked.any():
        marked[marked] = camera.on_image(camera.project(out[marked]))
        out[marked] = np.nan
    return out
