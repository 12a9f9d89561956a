"""What an annotator gives for one reference frame, as numpy arrays with fixed shapes.

Per joint ``k`` of a J-joint skeleton:

* ``uv_px[k]``: 2D position in image pixels (u = column, v = row); NaN where not annotated;
* ``visible[k]``: True if the joint is seen on the depth surface, False if occluded;
* ``depth_order[k]``: relative depth to the parent joint: ``+1`` farther from the camera than the
  parent, ``-1`` closer, ``0`` unknown or about equal (always 0 at the root);
* ``xyz_mm[k]``: optional 3D position in mm placed directly on the point cloud; NaN where not given;
* ``accepted[k]``: True where the 2D position is a guess the annotator accepted without moving it
  (the app's "accept guesses"), False where they clicked or dragged it; the lift weighs an
  accepted position below a click (:data:`handanno_core.lift.ACCEPTED_UV_WEIGHT`);
* ``outside[k]``: True where the annotator says the joint lies past the image's border, where
  nobody can click it (the hand leaves the view); such a joint has no 2D and no 3D position, and
  the lift places it like any joint without a position (a penalty keeping its projection off
  the image made the tune part's lifted references worse: benchmarks/HISTORY.md, stop 58).

A joint with neither 2D nor 3D is "unannotated": lifting still places it by the constraints and flags
it as low confidence. A frame is complete (:attr:`FrameAnnotation.complete`) when every joint is
annotated or marked outside the image.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


class AnnotationError(ValueError):
    """A malformed annotation: wrong joint count, bad values. The message says which."""


@dataclass
class FrameAnnotation:
    uv_px: np.ndarray  # (J, 2) float64, NaN = not annotated
    visible: np.ndarray  # (J,) bool
    depth_order: np.ndarray  # (J,) int8 in {-1, 0, +1}
    xyz_mm: np.ndarray  # (J, 3) float64, NaN = not placed in 3D
    accepted: np.ndarray = None  # type: ignore[assignment]  # (J,) bool; None: all False
    outside: np.ndarray = None  # type: ignore[assignment]  # (J,) bool; None: all False

    def __post_init__(self) -> None:
        if self.accepted is None:
            self.accepted = np.zeros(np.shape(self.uv_px)[0], dtype=bool)
        if self.outside is None:
            self.outside = np.zeros(np.shape(self.uv_px)[0], dtype=bool)

    @classmethod
    def empty(cls, num_joints: int) -> FrameAnnotation:
        return cls(
            uv_px=np.full((num_joints, 2), np.nan),
            visible=np.ones(num_joints, dtype=bool),
            depth_order=np.zeros(num_joints, dtype=np.int8),
            xyz_mm=np.full((num_joints, 3), np.nan),
        )

    @property
    def num_joints(self) -> int:
        return int(self.uv_px.shape[0])

    @property
    def has_2d(self) -> np.ndarray:
        """``(J,)`` bool: joint has a 2D position."""
        return np.all(np.isfinite(self.uv_px), axis=1)

    @property
    def has_3d(self) -> np.ndarray:
        """``(J,)`` bool: joint was placed in 3D."""
        return np.all(np.isfinite(self.xyz_mm), axis=1)

    @property
    def annotated(self) -> np.ndarray:
        """``(J,)`` bool: joint has a 2D or a 3D position."""
        return self.has_2d | self.has_3d

    @property
    def complete(self) -> np.ndarray:
        """``(J,)`` bool: joint annotated, or marked outside the image (nothing left to do)."""
        return self.annotated | self.outside

    def mark_outside(self, joints) -> None:
        """Mark ``joints`` (indices, or a ``(J,)`` bool mask) outside the image: their 2D and 3D
        positions and accepted flags are cleared (nobody can place a joint where the sensor saw
        nothing)."""
        self.uv_px[joints] = np.nan
        self.xyz_mm[joints] = np.nan
        self.accepted[joints] = False
        self.outside[joints] = True

    def validate(self, num_joints: int, where: str = "annotation") -> FrameAnnotation:
        """Check shapes and values against a J-joint skeleton; return self or raise AnnotationError."""
        expected = {
            "uv_px": (num_joints, 2),
            "visible": (num_joints,),
            "depth_order": (num_joints,),
            "xyz_mm": (num_joints, 3),
            "accepted": (num_joints,),
            "outside": (num_joints,),
        }
        for name, shape in expected.items():
            value = np.asarray(getattr(self, name))
            if value.shape != shape:
                raise AnnotationError(
                    f"{where}: {name} has shape {value.shape}, expected {shape} "
                    f"(skeleton has {num_joints} joints)"
                )
        for name in ("uv_px", "xyz_mm"):
            value = np.asarray(getattr(self, name), dtype=np.float64)
            partial = np.isnan(value).any(axis=1) & ~np.isnan(value).all(axis=1)
            if np.any(partial):
                raise AnnotationError(
                    f"{where}: {name} is half-NaN at joints {np.flatnonzero(partial).tolist()}"
                )
            if np.any(np.isinf(value)):
                raise AnnotationError(f"{where}: {name} has infinite values")
        if not np.all(np.isin(self.depth_order, (-1, 0, 1))):
            raise AnnotationError(f"{where}: depth_order must be -1, 0 or +1")
        self.uv_px = np.asarray(self.uv_px, dtype=np.float64)
        self.xyz_mm = np.asarray(self.xyz_mm, dtype=np.float64)
        self.visible = np.asarray(self.visible, dtype=bool)
        self.depth_order = np.asarray(self.depth_order, dtype=np.int8)
        # an accepted guess is a 2D position: the flag means nothing where there is none
        self.accepted = np.asarray(self.accepted, dtype=bool) & self.has_2d
        # a joint with a position is where it was placed, not outside the image
        self.outside = np.asarray(self.outside, dtype=bool) & ~self.annotated
        return self

    def copy(self) -> FrameAnnotation:
        return FrameAnnotation(
            self.uv_px.copy(),
            self.visible.copy(),
            self.depth_order.copy(),
            self.xyz_mm.copy(),
            self.accepted.copy(),
            self.outside.copy(),
        )

    # JSON: lists with None for NaN, so session.json stays valid JSON; "accepted" ("outside") only
    # where some joint is an accepted guess (marked outside the image): annotations written before
    # the flags read as all clicked (all inside).
    def to_json(self) -> dict:
        def rows(a: np.ndarray) -> list:
            return [None if np.isnan(r).any() else [round(float(x), 4) for x in r] for r in a]

        out = {
            "uv_px": rows(self.uv_px),
            "visible": [bool(x) for x in self.visible],
            "depth_order": [int(x) for x in self.depth_order],
            "xyz_mm": rows(self.xyz_mm),
        }
        if np.any(self.accepted):
            out["accepted"] = [bool(x) for x in self.accepted]
        if np.any(self.outside):
            out["outside"] = [bool(x) for x in self.outside]
        return out

    @classmethod
    def from_json(cls, data: dict, num_joints: int, where: str = "annotation") -> FrameAnnotation:
        try:

            def arr(rows: list, width: int) -> np.ndarray:
                return np.array(
                    [[np.nan] * width if r is None else [float(x) for x in r] for r in rows],
                    dtype=np.float64,
                ).reshape(len(rows), width)

            ann = cls(
                uv_px=arr(data["uv_px"], 2),
                visible=np.asarray(data["visible"], dtype=bool),
                depth_order=np.asarray(data["depth_order"], dtype=np.int8),
                xyz_mm=arr(data.get("xyz_mm") or [None] * len(data["uv_px"]), 3),
                accepted=np.asarray(
                    data.get("accepted") or [False] * len(data["uv_px"]), dtype=bool
                ),
                outside=np.asarray(data.get("outside") or [False] * len(data["uv_px"]), dtype=bool),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise AnnotationError(f"{where}: malformed annotation: {exc}") from exc
        return ann.validate(num_joints, where)
