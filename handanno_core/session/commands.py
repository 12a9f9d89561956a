"""The edit commands of a session (SLEEP-style ``check``/``inverse``/``apply``) and their parser."""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated, Any, ClassVar, Literal

import numpy as np
from pydantic import BaseModel, Field, TypeAdapter

from ..annotation import FrameAnnotation

if TYPE_CHECKING:
    from .session import Session


# ---------------------------------------------------------------------------------------------
# Commands: every edit, with an inverse for undo


class _Command(BaseModel):
    frame: int

    def check(self, session: Session) -> None:
        if not 0 <= self.frame < session.model.frames:
            raise ValueError(
                f"frame {self.frame} out of range (session has {session.model.frames} frames)"
            )

    def inverse(self, session: Session) -> Command:  # pragma: no cover - abstract
        raise NotImplementedError

    def apply(self, session: Session) -> None:  # pragma: no cover - abstract
        raise NotImplementedError

    # shared helpers
    def _joint_check(self, session: Session, joint: int) -> None:
        if not 0 <= joint < session.skeleton.num_joints:
            raise ValueError(
                f"joint {joint} out of range (skeleton has {session.skeleton.num_joints} joints)"
            )


class SetFrameAnnotation(_Command):
    """Replace a frame's whole annotation (``None`` deletes it). Used by import and the simulated annotator."""

    kind: Literal["set_frame"] = "set_frame"
    annotation: dict[str, Any] | None

    def check(self, session: Session) -> None:
        super().check(session)
        if self.annotation is not None:
            FrameAnnotation.from_json(
                self.annotation, session.skeleton.num_joints, f"frame {self.frame}"
            )

    def inverse(self, session: Session) -> Command:
        return SetFrameAnnotation(
            frame=self.frame, annotation=session.model.annotations.get(str(self.frame))
        )

    def apply(self, session: Session) -> None:
        if self.annotation is None:
            session.model.annotations.pop(str(self.frame), None)
        else:
            session.model.annotations[str(self.frame)] = self.annotation


class _JointEdit(_Command):
    joint: int

    def check(self, session: Session) -> None:
        super().check(session)
        self._joint_check(session, self.joint)

    def _annotation(self, session: Session) -> FrameAnnotation:
        return session.annotation(self.frame) or FrameAnnotation.empty(session.skeleton.num_joints)

    def _store(self, session: Session, ann: FrameAnnotation) -> None:
        session.model.annotations[str(self.frame)] = ann.to_json()

    def _old_state(self, session: Session) -> dict[str, Any]:
        ann = self._annotation(session)
        k = self.joint
        return {
            "uv_px": None if np.isnan(ann.uv_px[k]).any() else tuple(ann.uv_px[k]),
            "xyz_mm": None if np.isnan(ann.xyz_mm[k]).any() else tuple(ann.xyz_mm[k]),
            "visible": bool(ann.visible[k]),
            "order": int(ann.depth_order[k]),
            "accepted": bool(ann.accepted[k]),
            "outside": bool(ann.outside[k]),
        }

    #: the joint fields this edit changes; its inverse restores exactly these (per joint, per
    #: field), so undoing one annotator's 2D edit never reverts another's depth order on that joint.
    fields: ClassVar[tuple[str, ...]] = ()

    def changed_fields(self) -> tuple[str, ...]:
        return self.fields

    def inverse(self, session: Session) -> Command:
        old = self._old_state(session)
        keep = {f: old[f] for f in self.changed_fields()}
        return SetJointState(
            frame=self.frame,
            joint=self.joint,
            uv_px=keep.get("uv_px", _UNCHANGED),
            xyz_mm=keep.get("xyz_mm", _UNCHANGED),
            visible=keep.get("visible"),
            order=keep.get("order"),
            accepted=keep.get("accepted"),
            outside=keep.get("outside"),
        )


#: SetJointState's marker for "leave this position as it is" (``None`` clears it).
_UNCHANGED = "unchanged"


class SetJointState(_JointEdit):
    """Set several fields of one joint at once (the inverse of every single-joint edit).

    ``uv_px``/``xyz_mm``: a position, ``None`` (clear) or ``"unchanged"``; ``visible``/``order``/
    ``accepted``/``outside``: a value or ``None`` (unchanged). Entries written before the journal
    had checksums set the first four; entries written before a flag leave it unchanged.
    """

    kind: Literal["set_joint"] = "set_joint"
    uv_px: tuple[float, float] | None | Literal["unchanged"] = _UNCHANGED
    xyz_mm: tuple[float, float, float] | None | Literal["unchanged"] = _UNCHANGED
    visible: bool | None = None
    order: Literal[-1, 0, 1] | None = None
    accepted: bool | None = None
    outside: bool | None = None

    def changed_fields(self) -> tuple[str, ...]:
        out = [f for f in ("uv_px", "xyz_mm") if getattr(self, f) != _UNCHANGED]
        kept = ("visible", "order", "accepted", "outside")
        return (*out, *(f for f in kept if getattr(self, f) is not None))

    def check(self, session: Session) -> None:
        super().check(session)
        for name in ("uv_px", "xyz_mm"):
            value = getattr(self, name)
            if isinstance(value, tuple) and not np.all(np.isfinite(value)):
                raise ValueError(f"{name} must be finite")

    def apply(self, session: Session) -> None:
        ann = self._annotation(session)
        k = self.joint
        if self.uv_px != _UNCHANGED:
            ann.uv_px[k] = np.nan if self.uv_px is None else self.uv_px
        if self.xyz_mm != _UNCHANGED:
            ann.xyz_mm[k] = np.nan if self.xyz_mm is None else self.xyz_mm
        if self.visible is not None:
            ann.visible[k] = self.visible
        if self.order is not None:
            ann.depth_order[k] = self.order
        if self.accepted is not None:
            ann.accepted[k] = self.accepted
        if self.outside is not None:
            ann.outside[k] = self.outside
        self._store(session, ann)


class SetJoint2D(_JointEdit):
    """Set (or clear, with ``None``) one joint's 2D position in image pixels.

    ``accepted``: the position is a guess the annotator accepted without moving it (the app's
    "accept guesses"); a click or a drag leaves it False. Entries written before the flag are
    clicks. A position clears the joint's "outside the image" mark."""

    kind: Literal["set_2d"] = "set_2d"
    uv_px: tuple[float, float] | None
    accepted: bool = False
    fields: ClassVar[tuple[str, ...]] = ("uv_px", "accepted", "outside")

    def check(self, session: Session) -> None:
        super().check(session)
        if self.uv_px is not None and not np.all(np.isfinite(self.uv_px)):
            raise ValueError("2D position must be finite")

    def apply(self, session: Session) -> None:
        ann = self._annotation(session)
        ann.uv_px[self.joint] = np.nan if self.uv_px is None else self.uv_px
        ann.accepted[self.joint] = self.accepted and self.uv_px is not None
        if self.uv_px is not None:
            ann.outside[self.joint] = False
        self._store(session, ann)


class SetJoint3D(_JointEdit):
    """Place (or clear) one joint directly in 3D (mm); its 2D position follows by projection (and
    the joint is no longer marked outside the image)."""

    kind: Literal["set_3d"] = "set_3d"
    xyz_mm: tuple[float, float, float] | None
    fields: ClassVar[tuple[str, ...]] = ("uv_px", "xyz_mm", "accepted", "outside")

    def check(self, session: Session) -> None:
        super().check(session)
        if self.xyz_mm is not None and (
            not np.all(np.isfinite(self.xyz_mm)) or self.xyz_mm[2] <= 0
        ):
            raise ValueError("3D position must be finite and in front of the camera")

    def apply(self, session: Session) -> None:
        ann = self._annotation(session)
        if self.xyz_mm is None:
            ann.xyz_mm[self.joint] = np.nan
        else:
            ann.xyz_mm[self.joint] = self.xyz_mm
            ann.uv_px[self.joint] = session.camera.project(np.asarray(self.xyz_mm))
            ann.accepted[self.joint] = False  # placed by hand
            ann.outside[self.joint] = False
        self._store(session, ann)


class SetOutside(_JointEdit):
    """Mark one joint as lying past the image's border (``outside=True``: its 2D and 3D positions
    are cleared, since nobody can place it where the sensor saw nothing) or take the mark away."""

    kind: Literal["set_outside"] = "set_outside"
    outside: bool
    fields: ClassVar[tuple[str, ...]] = ("uv_px", "xyz_mm", "accepted", "outside")

    def apply(self, session: Session) -> None:
        ann = self._annotation(session)
        if self.outside:
            ann.mark_outside(self.joint)
        else:
            ann.outside[self.joint] = False
        self._store(session, ann)


class SetVisibility(_JointEdit):
    kind: Literal["set_visible"] = "set_visible"
    visible: bool
    fields: ClassVar[tuple[str, ...]] = ("visible",)

    def apply(self, session: Session) -> None:
        ann = self._annotation(session)
        ann.visible[self.joint] = self.visible
        self._store(session, ann)


class SetDepthOrder(_JointEdit):
    """Depth of the joint relative to its parent: -1 closer, 0 unknown, +1 farther."""

    kind: Literal["set_depth_order"] = "set_depth_order"
    order: Literal[-1, 0, 1]
    fields: ClassVar[tuple[str, ...]] = ("order",)

    def apply(self, session: Session) -> None:
        ann = self._annotation(session)
        ann.depth_order[self.joint] = self.order
        self._store(session, ann)


class SetReference(_Command):
    """Make a frame a reference (``is_reference=True``) or restore it to a propagated frame.

    ``parent`` is the parent to restore when un-making a reference; ``correction`` marks a frame
    that became a reference through review (counted as extra annotation cost).
    """

    kind: Literal["set_reference"] = "set_reference"
    is_reference: bool
    parent: int = -1
    correction: bool = False

    def check(self, session: Session) -> None:
        super().check(session)
        if not -1 <= self.parent < session.model.frames or self.parent == self.frame:
            raise ValueError(
                f"parent {self.parent} of frame {self.frame} out of range "
                f"(session has {session.model.frames} frames)"
            )

    def inverse(self, session: Session) -> Command:
        sel = session.model.selection
        was_ref = self.frame in sel.reference_frames
        old_parent = sel.parent[self.frame] if sel.parent else -1
        return SetReference(
            frame=self.frame,
            is_reference=was_ref,
            parent=old_parent,
            correction=self.frame in session.model.corrections,
        )

    def apply(self, session: Session) -> None:
        sel = session.model.selection
        refs = set(sel.reference_frames)
        if not sel.parent:
            sel.parent = [-1] * session.model.frames
        if self.is_reference:
            refs.add(self.frame)
            sel.parent[self.frame] = -1
        else:
            refs.discard(self.frame)
            sel.parent[self.frame] = self.parent
        sel.reference_frames = sorted(refs)
        corrections = set(session.model.corrections)
        if self.is_reference and self.correction:
            corrections.add(self.frame)
        else:
            corrections.discard(self.frame)
        session.model.corrections = sorted(corrections)


class SetReview(_Command):
    kind: Literal["set_review"] = "set_review"
    status: Literal["accepted", "flagged"] | None

    def inverse(self, session: Session) -> Command:
        return SetReview(frame=self.frame, status=session.model.review.get(str(self.frame)))  # type: ignore[arg-type]

    def apply(self, session: Session) -> None:
        if self.status is None:
            session.model.review.pop(str(self.frame), None)
        else:
            session.model.review[str(self.frame)] = self.status


class Batch(BaseModel):
    """Several commands applied (and undone) as one edit."""

    kind: Literal["batch"] = "batch"
    commands: list[Annotated[Any, Field()]]

    @property
    def frame(self) -> int:
        return self.parsed()[0].frame if self.commands else -1

    def parsed(self) -> list[Command]:
        return [
            c if isinstance(c, BaseModel) else _COMMAND_ADAPTER.validate_python(c)
            for c in self.commands
        ]

    def check(self, session: Session) -> None:
        for c in self.parsed():
            c.check(session)

    def inverse(self, session: Session) -> Command:
        # Inverses must see the state each command replaces: compute them while applying to a copy.
        raise NotImplementedError  # handled specially in Session._inverse_of

    def apply(self, session: Session) -> None:
        for c in self.parsed():
            c.apply(session)


Command = Annotated[
    SetFrameAnnotation
    | SetJointState
    | SetJoint2D
    | SetJoint3D
    | SetOutside
    | SetVisibility
    | SetDepthOrder
    | SetReference
    | SetReview
    | Batch,
    Field(discriminator="kind"),
]
_COMMAND_ADAPTER: TypeAdapter[Any] = TypeAdapter(Command)


def parse_command(data: dict[str, Any]) -> Command:
    return _COMMAND_ADAPTER.validate_python(data)
