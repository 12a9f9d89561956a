"""Several people's hands in one session: bone lengths per frame as a per-hand table.

The stages (propagation, refinement, the hand model) take ``bone_lengths_mm`` either as one
``(B,)`` set for every frame or as ``(N, B)``, each frame its hand's lengths (the session builds it
from its hand labels, :meth:`handanno_core.session.Session.frame_bone_lengths`). They work on the
table of the distinct sets and each frame's row in it; with one distinct set they run exactly the
code (and give exactly the numbers) of a one-hand session.
"""

from __future__ import annotations

import numpy as np

__all__ = ["BoneTable", "bone_table"]


class BoneTable:
    """``lengths`` (H, B) mm, the distinct bone-length sets; ``hand`` (N,) int, each frame's row
    (None when ``lengths`` has one row: every frame, whatever N)."""

    def __init__(self, lengths: np.ndarray, hand: np.ndarray | None):
        self.lengths = lengths
        self.hand = hand

    @property
    def single(self) -> bool:
        """One set for every frame."""
        return len(self.lengths) == 1

    def of(self, frame: int) -> np.ndarray:
        """``(B,)`` mm: frame ``frame``'s bone lengths."""
        return self.lengths[0 if self.hand is None else int(self.hand[frame])]

    def frames_of(self, h: int) -> np.ndarray:
        """Frames (sorted) whose bones are row ``h`` (only when not :attr:`single`)."""
        return np.flatnonzero(self.hand == h)

    def per_frame(self, frames: np.ndarray) -> np.ndarray:
        """``(len(frames), B)`` mm."""
        frames = np.asarray(frames, dtype=np.int64)
        rows = np.zeros(len(frames), dtype=np.int64) if self.hand is None else self.hand[frames]
        return self.lengths[rows]


def bone_table(bone_lengths_mm: np.ndarray, n: int, b: int) -> BoneTable:
    """The :class:`BoneTable` of ``bone_lengths_mm``: ``(B,)`` (every frame) or ``(N, B)`` mm.

    Raises ValueError on another shape."""
    bones = np.asarray(bone_lengths_mm, dtype=np.float64)
    if bones.shape == (b,):
        table, hand = bones[None], None
    elif bones.shape == (n, b) and n > 0:
        table, hand = np.unique(bones, axis=0, return_inverse=True)
        hand = np.asarray(hand, dtype=np.int64).ravel()
        if len(table) == 1:
            table, hand = bones[:1], None
    else:
        raise ValueError(f"bone_lengths_mm must be ({b},) or ({n}, {b}) mm, got {bones.shape}")
    return BoneTable(table, hand)
