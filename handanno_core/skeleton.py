"""Hand skeletons as data: joint names, parent array, bones, surface offsets, joint-angle limits.

Layouts: ``msra21`` (default), ``blender24``, ``icvl16``, ``nyu14``. A skeleton is a tree given by
its parent array (``-1`` for the root). A bone is a (parent, child) pair; bone ``b`` ends at joint
``bones[b, 1]``, so there are J - 1 bones.

Joint angles (thesis Eq. 5) are defined for a joint ``k`` with parent ``p`` and a single child ``c``:
with ``a = X_k - X_p`` (incoming bone) and ``b = X_c - X_k`` (outgoing bone),

* ``flexion`` = signed angle of ``b`` from ``a`` in the plane spanned by ``a`` and the palm normal
  (positive = bending towards the palm side);
* ``abduction`` = angle of ``b`` out of that plane (sideways), signed along ``a x n_perp``.

Along a finger the reference plane is carried from joint to joint (see :meth:`Skeleton.joint_angles`),
so a curled finger keeps measuring positive flexion.

The palm normal of a right hand is ``normalize((index_mcp - wrist) x (little_mcp - wrist))`` in the
OpenCV camera frame and points out of the palm; it is negated for a left hand.
"""

from __future__ import annotations

import functools
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np


def hand_rotation(
    wrist: np.ndarray, index: np.ndarray, little: np.ndarray, towards_fingers: np.ndarray
) -> np.ndarray:
    """Local-to-camera rotations ``(..., 3, 3)`` of the hand frame from landmarks ``(..., 3)``:
    ``y`` from ``wrist`` towards ``towards_fingers``, ``x`` towards the index side (``index`` minus
    ``little`` made perpendicular to ``y``), ``z = x cross y`` out of the palm (right hand)."""
    y = towards_fingers - wrist
    y = y / np.maximum(np.linalg.norm(y, axis=-1, keepdims=True), 1e-9)
    x = index - little
    x = x - np.sum(x * y, axis=-1, keepdims=True) * y
    x = x / np.maximum(np.linalg.norm(x, axis=-1, keepdims=True), 1e-9)
    z = np.cross(x, y)
    return np.stack([x, y, z], axis=-1)


@dataclass(frozen=True)
class Skeleton:
    """A hand skeleton layout. Arrays are indexed by joint (length J) or bone (length J - 1)."""

    name: str
    joint_names: tuple[str, ...]
    parents: tuple[int, ...]
    #: joint centre lies this far (mm) behind the observed surface (about the finger radius).
    surface_offsets_mm: tuple[float, ...]
    #: template bone lengths (mm) per bone, for initial scaling; None if the layout has none.
    template_bone_lengths_mm: tuple[float, ...] | None = None
    #: (wrist, index_mcp, little_mcp) joints that span the palm, or None (no angle limits).
    palm_joints: tuple[int, int, int] | None = None
    #: per joint (min, max) flexion and abduction in degrees; NaN where the joint has no limit.
    flexion_limits_deg: tuple[tuple[float, float], ...] | None = None
    abduction_limits_deg: tuple[tuple[float, float], ...] | None = None
    fingertips: tuple[int, ...] = field(default=())

    def __post_init__(self) -> None:
        j = len(self.joint_names)
        if len(self.parents) != j or len(self.surface_offsets_mm) != j:
            raise ValueError(f"skeleton {self.name}: per-joint arrays must have length {j}")
        if sum(p < 0 for p in self.parents) != 1:
            raise ValueError(f"skeleton {self.name}: exactly one root joint expected")
        if (
            self.template_bone_lengths_mm is not None
            and len(self.template_bone_lengths_mm) != j - 1
        ):
            raise ValueError(f"skeleton {self.name}: template needs {j - 1} bone lengths")

    # ------------------------------------------------------------------ structure
    @property
    def num_joints(self) -> int:
        return len(self.joint_names)

    @property
    def parent_array(self) -> np.ndarray:
        """``(J,)`` int array, -1 at the root."""
        return np.asarray(self.parents, dtype=np.int64)

    @property
    def root(self) -> int:
        return int(np.flatnonzero(self.parent_array < 0)[0])

    @property
    def bones(self) -> np.ndarray:
        """``(B, 2)`` int array of (parent, child) joints, in joint order of the child."""
        child = np.flatnonzero(self.parent_array >= 0)
        return np.stack([self.parent_array[child], child], axis=1)

    @property
    def topological_order(self) -> np.ndarray:
        """Joints ordered so that every parent comes before its children."""
        parents = self.parent_array
        depth = np.zeros(len(parents), dtype=np.int64)
        for j in range(len(parents)):
            k = j
            while parents[k] >= 0:
                depth[j] += 1
                k = parents[k]
        return np.argsort(depth, kind="stable")

    def children(self, joint: int) -> np.ndarray:
        return np.flatnonzero(self.parent_array == joint)

    @property
    def finger_bases(self) -> np.ndarray:
        """``(J,)`` int: each joint's ancestor that is a child of the root, the first joint of its
        finger (the root maps to itself)."""
        parents = self.parent_array
        base = np.arange(len(parents))
        for j in range(len(parents)):
            while parents[base[j]] >= 0 and parents[parents[base[j]]] >= 0:
                base[j] = parents[base[j]]
        return base

    @property
    def has_finger_segments(self) -> bool:
        """Every fingertip is at least 3 bones from the root: the fingers' proximal, middle and
        distal segments are bones, so the capsule hand model (:mod:`handanno_core.handmodel`) can
        stand for the hand. NYU's 14 joints (palm centre -> middle -> tip) are not: their
        palm-to-middle bone runs through the palm."""
        parents = self.parent_array
        for tip in self.fingertips or ():
            depth, k = 0, int(tip)
            while parents[k] >= 0:
                depth, k = depth + 1, int(parents[k])
            if depth < 3:
                return False
        return bool(self.fingertips)

    @property
    def angle_joints(self) -> np.ndarray:
        """Joints with angle limits, ``(A,)``; their single child is ``angle_children``."""
        if self.flexion_limits_deg is None:
            return np.zeros(0, dtype=np.int64)
        limits = np.asarray(self.flexion_limits_deg)
        return np.flatnonzero(np.isfinite(limits[:, 0]))

    @property
    def angle_children(self) -> np.ndarray:
        return np.asarray([self.children(k)[0] for k in self.angle_joints], dtype=np.int64)

    # ------------------------------------------------------------------ measurements
    def bone_vectors(self, poses_mm: np.ndarray) -> np.ndarray:
        """``(..., J, 3)`` poses -> ``(..., B, 3)`` bone vectors child - parent."""
        b = self.bones
        return poses_mm[..., b[:, 1], :] - poses_mm[..., b[:, 0], :]

    def bone_lengths(self, poses_mm: np.ndarray) -> np.ndarray:
        """``(..., J, 3)`` poses -> ``(..., B)`` bone lengths in mm."""
        return np.linalg.norm(self.bone_vectors(np.asarray(poses_mm, dtype=np.float64)), axis=-1)

    def estimate_bone_lengths(self, poses_mm: np.ndarray) -> np.ndarray:
        """Robust (median) bone lengths ``(B,)`` in mm from poses ``(N, J, 3)``; NaN poses ignored."""
        lengths = self.bone_lengths(
            np.asarray(poses_mm, dtype=np.float64).reshape(-1, self.num_joints, 3)
        )
        return np.nanmedian(lengths, axis=0)

    def palm_normal(self, poses_mm: np.ndarray, right_hand: bool = True) -> np.ndarray:
        """Unit palm normals ``(..., 3)`` pointing out of the palm."""
        if self.palm_joints is None:
            raise ValueError(f"skeleton {self.name} defines no palm joints")
        w, i, lt = self.palm_joints
        n = np.cross(
            poses_mm[..., i, :] - poses_mm[..., w, :], poses_mm[..., lt, :] - poses_mm[..., w, :]
        )
        n = n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-9)
        return n if right_hand else -n

    def palm_rotation(self, poses_mm: np.ndarray) -> np.ndarray:
        """Rotations ``(..., 3, 3)`` of the palm (:func:`hand_rotation` of the wrist, index and
        little MCP of :attr:`palm_joints`, ``y`` towards the midpoint of the two MCPs)."""
        if self.palm_joints is None:
            raise ValueError(f"skeleton {self.name} defines no palm joints")
        w, i, lt = self.palm_joints
        x = poses_mm
        return hand_rotation(x[..., w, :], x[..., i, :], x[..., lt, :],
                             0.5 * (x[..., i, :] + x[..., lt, :]))  # fmt: skip

    def palm_coordinates(self, poses_mm: np.ndarray) -> np.ndarray:
        """``(..., J, 3)`` mm: the joints of ``poses_mm`` relative to the root, in the palm's frame
        (:meth:`palm_rotation`): the pose without its place and orientation."""
        x = np.asarray(poses_mm, dtype=np.float64)
        rel = x - x[..., self.root, None, :]
        return np.einsum("...jk,...kc->...jc", rel, self.palm_rotation(x))

    def bone_directions(self, poses_mm: np.ndarray, right_hand: bool = True) -> np.ndarray:
        """``(..., A, 3)`` unit vectors: the bone leaving each joint of ``angle_joints`` in that
        joint's frame (along the incoming bone, towards the palm, lateral), the frame
        :meth:`joint_angles` measures flexion and abduction in.

        At the first joint of a finger (MCP, thumb CMC) the towards-the-palm direction is the palm
        normal made perpendicular to the incoming bone. Further along the finger the lateral axis is
        transported along the chain (the parent joint's lateral axis made perpendicular to the
        incoming bone) rather than re-projecting the palm normal, which would flip sign once a
        finger curls past 90 degrees (the DIP of a fist) and is undefined when a bone points along
        the palm normal.
        """
        poses = np.asarray(poses_mm, dtype=np.float64)
        parents = self.parent_array
        normal = self.palm_normal(poses, right_hand)
        lateral_of: dict[int, np.ndarray] = {}
        out = []
        for k, c in zip(self.angle_joints, self.angle_children, strict=True):
            p = int(parents[k])
            a = _unit(poses[..., k, :] - poses[..., p, :])
            if p in lateral_of:
                lateral = _unit(
                    lateral_of[p] - np.sum(lateral_of[p] * a, axis=-1, keepdims=True) * a
                )
            else:
                n_perp = _unit(normal - np.sum(normal * a, axis=-1, keepdims=True) * a)
                lateral = np.cross(a, n_perp)
            lateral_of[int(k)] = lateral
            n_perp = np.cross(lateral, a)
            b = _unit(poses[..., c, :] - poses[..., k, :])
            out.append(
                np.stack(
                    [
                        np.sum(b * a, axis=-1),
                        np.sum(b * n_perp, axis=-1),
                        np.sum(b * lateral, axis=-1),
                    ],
                    axis=-1,
                )
            )
        return np.stack(out, axis=-2)

    def joint_angles(
        self, poses_mm: np.ndarray, right_hand: bool = True
    ) -> tuple[np.ndarray, np.ndarray]:
        """Flexion and abduction in degrees, each ``(..., A)`` for the joints in ``angle_joints``,
        of the bones leaving them in their frames (:meth:`bone_directions`)."""
        d = self.bone_directions(poses_mm, right_hand)
        along, towards_palm, side = d[..., 0], d[..., 1], d[..., 2]
        flexion = np.degrees(np.arctan2(towards_palm, along))
        abduction = np.degrees(np.arctan2(side, np.hypot(along, towards_palm)))
        return flexion, abduction

    def angle_limits(self) -> tuple[np.ndarray, np.ndarray]:
        """``(A, 2)`` flexion and abduction limits in degrees for ``angle_joints``."""
        k = self.angle_joints
        return np.asarray(self.flexion_limits_deg)[k], np.asarray(self.abduction_limits_deg)[k]

    def learned_angle_ranges(self) -> tuple[np.ndarray, np.ndarray] | None:
        """``(A, 2)`` flexion and abduction ranges (degrees) observed on real recorded motion
        (``data/angle_ranges.json``, robust percentiles), or None if the layout has none. Joints
        the table does not list get NaN rows."""
        table = _angle_table().get(self.name)
        if table is None:
            return None
        fl = np.full((len(self.angle_joints), 2), np.nan)
        ab = np.full((len(self.angle_joints), 2), np.nan)
        for i, k in enumerate(self.angle_joints):
            row = table["joints"].get(self.joint_names[k])
            if row is not None:
                fl[i], ab[i] = row["flexion"], row["abduction"]
        return fl, ab

    def angle_ranges(self, right_hand: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """``(A, 2)`` flexion and abduction ranges (degrees) used as *soft* limits by the lift:
        the union of :meth:`angle_limits` (anatomical, hand-set) and :meth:`learned_angle_ranges`
        (what real hands were recorded doing). A pose inside is free; beyond it the lift's
        penalty grows quadratically. The table is for a right hand; a left hand, measured with
        ``right_hand=False``, has the same flexion and negated abduction ranges."""
        fl, ab = self.angle_limits()
        learned = self.learned_angle_ranges()
        if learned is not None:
            out = []
            for lim, obs in zip((fl, ab), learned, strict=True):
                lo = np.fmin(lim[:, 0], obs[:, 0])
                hi = np.fmax(lim[:, 1], obs[:, 1])
                out.append(np.stack([lo, hi], axis=1))
            fl, ab = out
        if not right_hand:
            ab = -ab[:, ::-1]
        return fl, ab

    def angle_range_violation_deg(
        self, poses_mm: np.ndarray, right_hand: bool = True
    ) -> np.ndarray:
        """``(..., A)`` degrees by which each joint's flexion or abduction (whichever is worse)
        lies outside :meth:`angle_ranges`; 0 inside."""
        flex, abd = self.joint_angles(poses_mm, right_hand)
        fl, ab = self.angle_ranges(right_hand)
        v_f = np.maximum(np.maximum(fl[:, 0] - flex, flex - fl[:, 1]), 0.0)
        v_a = np.maximum(np.maximum(ab[:, 0] - abd, abd - ab[:, 1]), 0.0)
        return np.maximum(v_f, v_a)

    def surface_groups(self) -> np.ndarray:
        """``(J,)`` int group per joint for surface-offset calibration: joints of the same kind
        (same position along their chain: 0 = root/palm, 1 = first joint off the root, 2, 3 ...,
        tips their own group) share an offset correction."""
        par = self.parent_array
        level = np.zeros(self.num_joints, dtype=np.int64)
        for j in range(self.num_joints):
            k = j
            while par[k] >= 0:
                level[j] += 1
                k = par[k]
        tips = np.asarray(self.fingertips, dtype=np.int64)
        groups = level.copy()
        groups[tips] = -1
        return groups


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def default_angle_ranges_path() -> Path:
    """The packaged table of learned angle ranges and bone lengths per layout."""
    return Path(__file__).resolve().parent / "data" / "angle_ranges.json"


@functools.cache
def _angle_table() -> dict:
    """``layout -> {"joints": {name: {"flexion": [lo, hi], "abduction": [lo, hi]}},
    "bone_lengths_mm": [...]}`` from :func:`default_angle_ranges_path` ({} if absent)."""
    path = default_angle_ranges_path()
    if not path.is_file():
        return {}
    return json.loads(path.read_text())["layouts"]


def _learned_limits(
    name: str, joint_names: tuple[str, ...]
) -> tuple[tuple[tuple[float, float], ...] | None, tuple[tuple[float, float], ...] | None]:
    """Per-joint learned (flexion, abduction) limits of a layout that has no hand-set ones."""
    table = _angle_table().get(name)
    if table is None:
        return None, None
    rows = [table["joints"].get(n) for n in joint_names]
    fl = tuple(tuple(r["flexion"]) if r else _NAN for r in rows)
    ab = tuple(tuple(r["abduction"]) if r else _NAN for r in rows)
    return fl, ab  # type: ignore[return-value]


def _learned_bones(name: str) -> tuple[float, ...] | None:
    table = _angle_table().get(name)
    return None if table is None else tuple(float(b) for b in table["bone_lengths_mm"])


#: FPHA joint order (wrist, TMCP, IMCP, MMCP, RMCP, PMCP, then (PIP, DIP, TIP) of thumb, index,
#: middle, ring, pinky) -> MSRA-21: ``msra = fpha[:, FPHA_TO_MSRA21]``. FPHA's thumb "MCP" is the
#: CMC-side joint, MSRA's ``thumb_cmc``; FPHA's thumb PIP/DIP are MSRA's ``thumb_mcp``/``thumb_ip``.
FPHA_TO_MSRA21 = (0, 2, 9, 10, 11, 3, 12, 13, 14, 4, 15, 16, 17, 5, 18, 19, 20, 1, 6, 7, 8)


_NAN = (float("nan"), float("nan"))
_MCP, _PIP, _DIP = (0.0, 90.0), (0.0, 110.0), (0.0, 90.0)
_ABD_MCP, _ABD_HINGE = (-15.0, 15.0), (-5.0, 5.0)

MSRA21 = Skeleton(
    name="msra21",
    joint_names=(
        "wrist",
        "index_mcp",
        "index_pip",
        "index_dip",
        "index_tip",
        "middle_mcp",
        "middle_pip",
        "middle_dip",
        "middle_tip",
        "ring_mcp",
        "ring_pip",
        "ring_dip",
        "ring_tip",
        "little_mcp",
        "little_pip",
        "little_dip",
        "little_tip",
        "thumb_cmc",
        "thumb_mcp",
        "thumb_ip",
        "thumb_tip",
    ),
    parents=(-1, 0, 1, 2, 3, 0, 5, 6, 7, 0, 9, 10, 11, 0, 13, 14, 15, 0, 17, 18, 19),
    surface_offsets_mm=(
        15.0,
        9.0,
        8.0,
        7.0,
        0.0,
        9.0,
        8.0,
        7.0,
        0.0,
        9.0,
        8.0,
        7.0,
        0.0,
        8.0,
        7.0,
        6.0,
        0.0,
        12.0,
        10.0,
        8.0,
        0.0,
    ),
    template_bone_lengths_mm=(
        80.0,
        40.0,
        24.0,
        20.0,
        78.0,
        45.0,
        28.0,
        22.0,
        74.0,
        42.0,
        27.0,
        21.0,
        68.0,
        33.0,
        20.0,
        19.0,
        38.0,
        42.0,
        32.0,
        26.0,
    ),
    palm_joints=(0, 1, 13),
    flexion_limits_deg=(
        _NAN,
        _MCP,
        _PIP,
        _DIP,
        _NAN,
        _MCP,
        _PIP,
        _DIP,
        _NAN,
        _MCP,
        _PIP,
        _DIP,
        _NAN,
        _MCP,
        _PIP,
        _DIP,
        _NAN,
        (-30.0, 90.0),
        (-20.0, 80.0),
        (-20.0, 90.0),
        _NAN,
    ),
    abduction_limits_deg=(
        _NAN,
        _ABD_MCP,
        _ABD_HINGE,
        _ABD_HINGE,
        _NAN,
        _ABD_MCP,
        _ABD_HINGE,
        _ABD_HINGE,
        _NAN,
        _ABD_MCP,
        _ABD_HINGE,
        _ABD_HINGE,
        _NAN,
        _ABD_MCP,
        _ABD_HINGE,
        _ABD_HINGE,
        _NAN,
        (-60.0, 60.0),
        (-30.0, 30.0),
        (-20.0, 20.0),
        _NAN,
    ),
    fingertips=(4, 8, 12, 16, 20),
)

BLENDER24 = Skeleton(
    name="blender24",
    joint_names=(
        "CT",
        "T1",
        "T2",
        "T3",
        "CI",
        "I1",
        "I2",
        "I3",
        "I4",
        "CM",
        "M1",
        "M2",
        "M3",
        "M4",
        "CR",
        "R1",
        "R2",
        "R3",
        "R4",
        "CP",
        "P1",
        "P2",
        "P3",
        "P4",
    ),
    parents=(4, 0, 1, 2, 9, 4, 5, 6, 7, -1, 9, 10, 11, 12, 9, 14, 15, 16, 17, 14, 19, 20, 21, 22),
    surface_offsets_mm=(
        20.0,
        10.0,
        8.0,
        2.0,
        15.0,
        9.0,
        8.0,
        7.0,
        2.0,
        15.0,
        9.0,
        8.0,
        7.0,
        2.0,
        15.0,
        9.0,
        8.0,
        7.0,
        2.0,
        15.0,
        8.0,
        7.0,
        6.0,
        2.0,
    ),
    fingertips=(3, 8, 13, 18, 23),
)

_ICVL_NAMES = (
    "palm",
    "thumb_root",
    "thumb_mid",
    "thumb_tip",
    "index_root",
    "index_mid",
    "index_tip",
    "middle_root",
    "middle_mid",
    "middle_tip",
    "ring_root",
    "ring_mid",
    "ring_tip",
    "little_root",
    "little_mid",
    "little_tip",
)
_NYU_NAMES = (
    "little_tip",
    "little_mid",
    "ring_tip",
    "ring_mid",
    "middle_tip",
    "middle_mid",
    "index_tip",
    "index_mid",
    "thumb_tip",
    "thumb_mid",
    "thumb_root",
    "wrist1",
    "wrist2",
    "palm",
)

ICVL16 = Skeleton(
    name="icvl16",
    joint_names=_ICVL_NAMES,
    parents=(-1, 0, 1, 2, 0, 4, 5, 0, 7, 8, 0, 10, 11, 0, 13, 14),
    surface_offsets_mm=(15.0,) + (9.0, 8.0, 0.0) * 5,
    template_bone_lengths_mm=_learned_bones("icvl16"),
    palm_joints=(0, 4, 13),
    flexion_limits_deg=_learned_limits("icvl16", _ICVL_NAMES)[0],
    abduction_limits_deg=_learned_limits("icvl16", _ICVL_NAMES)[1],
    fingertips=(3, 6, 9, 12, 15),
)

NYU14 = Skeleton(
    name="nyu14",
    joint_names=_NYU_NAMES,
    parents=(1, 13, 3, 13, 5, 13, 7, 13, 9, 10, 13, 13, 13, -1),
    surface_offsets_mm=(0.0, 8.0, 0.0, 8.0, 0.0, 8.0, 0.0, 8.0, 0.0, 8.0, 10.0, 15.0, 15.0, 15.0),
    template_bone_lengths_mm=_learned_bones("nyu14"),
    # wrist2 (thumb side), palm, wrist1 (little side): the palm-fixed triangle, oriented like
    # MSRA's (wrist, index_mcp, little_mcp) (measured on the NYU labels: wrist2 is 15 mm nearer
    # the thumb root than wrist1)
    palm_joints=(12, 13, 11),
    flexion_limits_deg=_learned_limits("nyu14", _NYU_NAMES)[0],
    abduction_limits_deg=_learned_limits("nyu14", _NYU_NAMES)[1],
    fingertips=(0, 2, 4, 6, 8),
)

SKELETONS: dict[str, Skeleton] = {s.name: s for s in (MSRA21, BLENDER24, ICVL16, NYU14)}


def get_skeleton(name: str) -> Skeleton:
    """Look a layout up by name (``msra21``, ``blender24``, ``icvl16``, ``nyu14``)."""
    try:
        return SKELETONS[name.lower()]
    except KeyError:
        raise ValueError(
            f"unknown skeleton layout {name!r}; known: {', '.join(SKELETONS)}"
        ) from None
