"""Synthetic depth videos of an articulated right hand, with exact ground truth.

The benchmark data every stage is measured on. A right hand in the MSRA 21-joint layout is posed by
forward kinematics from joint angles (flexion/abduction inside anatomical limits), moved through a
sequence of gestures (open, fist, point, pinch, thumbs-up, spread, counting ...) with holds, revisits
of earlier gestures and global poses, and a global rotation that shows the palm and the back of the
hand. Each frame is rendered by exact ray casting of capsules (finger bones, palm, forearm) and an
ellipsoid (palm) at the MSRA camera, then corrupted by sensor-like noise: ~1 mm Gaussian depth noise,
dropout at depth discontinuities and a few small holes. Background is 0 (no measurement).

Output: the MSRA-2015 layout (``%06d_depth.bin`` + ``joint.txt``) plus ``camera.json`` and
``synth.json`` (the keyframe schedule: which gesture when, which keyframes are revisits).

Local hand frame (before the global rotation): origin at the wrist, ``+y`` towards the fingers,
``+x`` towards the thumb/index side, ``+z`` the palm normal of :meth:`Skeleton.palm_normal` (out of
the palm). Joint angles are parameterised exactly as :meth:`Skeleton.joint_angles` measures them, so the
generated poses satisfy the skeleton's limits by construction (checked in the tests).

Also here: the simulated annotator used by benchmarks (:func:`simulate_annotation`,
:func:`simulate_annotations`), which is allowed to read ground truth.
"""

from __future__ import annotations

import functools
import json
import os
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from multiprocessing import get_context
from pathlib import Path

import numpy as np

from .annotation import FrameAnnotation
from .camera import MSRA_CAMERA, CameraIntrinsics
from .sampling import visible_by_depth
from .skeleton import MSRA21, Skeleton

# ---------------------------------------------------------------------------- parameters
#: articulation parameter layout (degrees): 4 per finger (index, middle, ring, little):
#: MCP flexion, MCP abduction, PIP flexion, DIP flexion; then the thumb: CMC flexion, CMC
#: abduction, MCP flexion, MCP abduction, IP flexion.
PARAM_NAMES: tuple[str, ...] = tuple(
    f"{f}_{p}"
    for f in ("index", "middle", "ring", "little")
    for p in ("mcp_flex", "mcp_abd", "pip_flex", "dip_flex")
) + ("thumb_cmc_flex", "thumb_cmc_abd", "thumb_mcp_flex", "thumb_mcp_abd", "thumb_ip_flex")
NUM_PARAMS = len(PARAM_NAMES)

# Limits used for generation: inside MSRA21.angle_limits() with a 1.5 degree margin (fingers:
# MCP 0-90, PIP 0-110, DIP 0-90, MCP abduction +-15; thumb ranges of its own, narrower than the
# skeleton's, to stay natural).
_FINGER_LO = (0.0, -13.5, 0.0, 0.0)
_FINGER_HI = (88.5, 13.5, 108.5, 88.5)
_THUMB_LO = (-25.0, -45.0, -15.0, -15.0, -15.0)
_THUMB_HI = (75.0, 50.0, 70.0, 15.0, 85.0)
PARAM_LO = np.array(_FINGER_LO * 4 + _THUMB_LO)
PARAM_HI = np.array(_FINGER_HI * 4 + _THUMB_HI)

#: joints of each chain (MSRA21): a chain starts at a joint whose parent is the wrist.
_CHAINS = ((1, 2, 3, 4), (5, 6, 7, 8), (9, 10, 11, 12), (13, 14, 15, 16), (17, 18, 19, 20))
#: parameter indices (flexion, abduction or None) of the joints 1..3 of each chain.
_CHAIN_PARAMS = tuple(
    ((4 * f, 4 * f + 1), (4 * f + 2, None), (4 * f + 3, None)) for f in range(4)
) + (((16, 17), (18, 19), (20, None)),)

#: finger surface radii (mm) of the proximal, middle and distal bone; the distal capsule ends one
#: radius before the tip, so its cap reaches the tip joint (tips lie on the surface).
_FINGER_RADII = np.array(
    [[8.5, 7.5, 6.5], [8.7, 7.7, 6.7], [8.2, 7.3, 6.4], [7.3, 6.5, 5.6], [11.0, 9.5, 8.2]]
)
_PALM_HALF_THICKNESS = 12.5
_FOREARM_RADIUS = 22.0
_FOREARM_SPREAD = 8.0
_FOREARM_LENGTH = 150.0
#: an arm that points at the camera is cut this far (mm, z) in front of it (a real one leaves the
#: sensor's field of view or its minimum range there)
NEAR_CLIP_MM = 60.0
#: a sleeve: one round capsule from this far up the forearm, wider than the arm by this much
_SLEEVE_START_MM = 70.0
_SLEEVE_EXTRA_MM = 6.0
#: forearm length (mm, wrist towards elbow) used when the arm is drawn at an angle of its own;
#: long enough to leave a 320x240 image at hand distance, like a real arm
ARM_LENGTH_MM = 260.0


@dataclass(frozen=True)
class HandModel:
    """A hand's fixed geometry (mm), in the local hand frame (see module docstring)."""

    bone_lengths_mm: np.ndarray  # (20,) MSRA21 bone order
    local_base: np.ndarray  # (21, 3) wrist, the 4 MCPs and the thumb CMC (other rows unused)
    palm_centre: np.ndarray  # (3,) rotation centre of the global motion
    palm_normal: np.ndarray  # (3,) unit, = skeleton palm normal in the local frame (+z)
    #: (5, 3) surface radii (mm) of the proximal, middle, distal bone of index..little, thumb
    finger_radii: np.ndarray = field(default_factory=lambda: _FINGER_RADII.copy())
    palm_half_thickness_mm: float = _PALM_HALF_THICKNESS
    forearm_radius_mm: float = _FOREARM_RADIUS


def make_hand_model(seed: int = 0, skeleton: Skeleton = MSRA21) -> HandModel:
    """A per-seed hand: template bone lengths times a global scale (0.92-1.08) and +-2.5 % jitter."""
    rng = np.random.default_rng([seed, 101])
    template = np.asarray(skeleton.template_bone_lengths_mm, dtype=np.float64)
    scale = rng.uniform(0.92, 1.08)
    jitter = np.clip(rng.normal(1.0, 0.025, len(template)), 0.95, 1.05)
    return build_hand_model(template * scale * jitter, scale)


# Hand-shape variation (make_varied_hand_model), from published hand measurements:
# * overall size: hand length of adults is about 180 mm (women) to 194 mm (men) with SDs of about
#   9 mm (ANSUR II: Gordon et al., "2012 Anthropometric Survey of U.S. Army Personnel", NATICK
#   TR-15/007, 2014), so 0.8-1.2x of the template spans small women's to large men's hands;
# * per-finger proportions: phalanx and metacarpal lengths vary with coefficients of variation of
#   about 6-9 % (Buryanov & Kotiuk, "Proportions of hand segments", Int. J. Morphol. 28(3):755-758,
#   2010); most of that is overall size, so after the global scale each finger gets a factor of
#   SD 3.5 % and each bone one of SD 3 %;
# * finger thickness: finger breadths at the PIP and DIP joints (e.g. index PIP about 21 mm in men,
#   18.5 mm in women, SDs about 1.1-1.3 mm, i.e. 6 %: Greiner, "Hand Anthropometry of U.S. Army
#   Personnel", NATICK TR-92/011, 1991): radii scale with size, times a per-hand factor of SD 6 %
#   (slender or stubby fingers) and a per-finger factor of SD 3 %;
# * hand breadth relative to length: SD about 5 % (same surveys): the MCP spread gets its own factor.
SHAPE_FINGER_SD = 0.035
SHAPE_BONE_SD = 0.03
SHAPE_RADIUS_SD = 0.06
SHAPE_RADIUS_FINGER_SD = 0.03
SHAPE_BREADTH_SD = 0.05


def make_varied_hand_model(
    seed: int, scale: float | None = None, skeleton: Skeleton = MSRA21
) -> HandModel:
    """A hand drawn from adult hand measurements (see the comment above): overall ``scale``
    (None: uniform 0.8-1.2), per-finger and per-bone proportions, finger radii and palm breadth.
    Factors are normal with the SDs above, clipped at 2.5 SD."""
    rng = np.random.default_rng([seed, 102])
    template = np.asarray(skeleton.template_bone_lengths_mm, dtype=np.float64)
    size = rng.uniform(0.8, 1.2) if scale is None else float(scale)

    def factor(sd: float, n: int) -> np.ndarray:
        return 1.0 + np.clip(rng.normal(0.0, sd, n), -2.5 * sd, 2.5 * sd)

    per_finger = np.repeat(factor(SHAPE_FINGER_SD, 5), 4)  # bones are 4 per finger (MSRA21)
    lengths = template * size * per_finger * factor(SHAPE_BONE_SD, len(template))
    radii = (
        _FINGER_RADII
        * size
        * factor(SHAPE_RADIUS_SD, 1)
        * factor(SHAPE_RADIUS_FINGER_SD, 5)[:, None]
    )
    breadth = float(factor(SHAPE_BREADTH_SD, 1)[0])
    return build_hand_model(lengths, size * breadth, radii, thickness_scale=size)


def build_hand_model(
    lengths: np.ndarray,
    spread_scale: float = 1.0,
    finger_radii: np.ndarray | None = None,
    thickness_scale: float = 1.0,
) -> HandModel:
    """A :class:`HandModel` from bone lengths ``(20,)`` mm (MSRA21 order), the MCP spread's scale,
    finger radii ``(5, 3)`` mm (None: the template's) and a palm/forearm thickness scale."""
    lengths = np.asarray(lengths, dtype=np.float64)
    base = np.zeros((21, 3))
    # MCPs spread across ~52 mm (scaled), slight transverse arch (middle/ring dorsal, -z).
    xs = np.array([26.0, 8.0, -10.0, -26.0]) * spread_scale
    zs = np.array([0.0, -3.0, -2.0, 0.0]) * spread_scale
    for f, (mcp, bone) in enumerate(zip((1, 5, 9, 13), (0, 4, 8, 12), strict=True)):
        length = lengths[bone]
        y = np.sqrt(length**2 - xs[f] ** 2 - zs[f] ** 2)
        base[mcp] = (xs[f], y, zs[f])
    cmc_dir = np.array([0.62, 0.68, 0.39])
    base[17] = cmc_dir / np.linalg.norm(cmc_dir) * lengths[16]
    n = np.cross(base[1], base[13])
    n /= np.linalg.norm(n)
    palm_centre = np.array([0.0, 0.5 * base[[1, 5, 9, 13], 1].mean(), 0.0])
    radii = _FINGER_RADII.copy() if finger_radii is None else np.asarray(finger_radii, float)
    return HandModel(
        lengths,
        base,
        palm_centre,
        n,
        radii,
        _PALM_HALF_THICKNESS * thickness_scale,
        _FOREARM_RADIUS * thickness_scale,
    )


# ---------------------------------------------------------------------------- kinematics
def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def _step(
    a: np.ndarray, lateral: np.ndarray, flex_deg: np.ndarray, abd_deg: np.ndarray
) -> np.ndarray:
    """Direction of the outgoing bone from incoming unit direction ``a`` and lateral axis (N, 3)."""
    n_perp = np.cross(lateral, a)
    f = np.radians(flex_deg)[..., None]
    b = np.radians(abd_deg)[..., None]
    return np.cos(b) * (np.cos(f) * a + np.sin(f) * n_perp) + np.sin(b) * lateral


def _transport(lateral: np.ndarray, a: np.ndarray) -> np.ndarray:
    return _unit(lateral - np.sum(lateral * a, axis=-1, keepdims=True) * a)


def local_pose(model: HandModel, params_deg: np.ndarray) -> np.ndarray:
    """Joint positions ``(N, 21, 3)`` mm in the local hand frame from parameters ``(N, 21)`` deg."""
    params = np.atleast_2d(np.asarray(params_deg, dtype=np.float64))
    n_frames = len(params)
    pose = np.zeros((n_frames, 21, 3))
    pose[:] = model.local_base
    normal = np.broadcast_to(model.palm_normal, (n_frames, 3))
    lengths = model.bone_lengths_mm
    for chain, pidx in zip(_CHAINS, _CHAIN_PARAMS, strict=True):
        a = _unit(pose[:, chain[0]] - pose[:, 0])
        lateral = _unit(np.cross(a, normal - np.sum(normal * a, axis=-1, keepdims=True) * a))
        for k in range(3):
            joint, child = chain[k], chain[k + 1]
            fi, ai = pidx[k]
            abd = params[:, ai] if ai is not None else np.zeros(n_frames)
            if k > 0:
                lateral = _transport(lateral, a)
            b = _step(a, lateral, params[:, fi], abd)
            pose[:, child] = pose[:, joint] + lengths[child - 1] * b
            a = b
    return pose


def rotation_matrices(yaw_pitch_roll_deg: np.ndarray) -> np.ndarray:
    """``(N, 3)`` yaw, pitch, roll (deg) -> ``(N, 3, 3)`` local-hand-frame to camera rotations.

    Yaw 0: palm facing the camera, fingers up; yaw 180: back of the hand to the camera. The
    rotation is ``Rz(roll) Rx(pitch) Ry(yaw) B`` with ``B`` mapping local (x, y, z) to camera
    (x, -y, -z).
    """
    ang = np.radians(np.atleast_2d(yaw_pitch_roll_deg))
    cy, sy = np.cos(ang[:, 0]), np.sin(ang[:, 0])
    cp, sp = np.cos(ang[:, 1]), np.sin(ang[:, 1])
    one, zero = np.ones_like(cy), np.zeros_like(cy)
    ry = np.stack([cy, zero, sy, zero, one, zero, -sy, zero, cy], -1).reshape(-1, 3, 3)
    rx = np.stack([one, zero, zero, zero, cp, -sp, zero, sp, cp], -1).reshape(-1, 3, 3)
    base = np.diag([1.0, -1.0, -1.0])
    return _rotation_z(ang[:, 2]) @ rx @ ry @ base


def _rotation_z(angle_rad: np.ndarray) -> np.ndarray:
    """``(N, 3, 3)`` rotations about the camera's z axis by ``angle_rad`` ``(N,)`` (in the image:
    from +x towards +y)."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    one, zero = np.ones_like(c), np.zeros_like(c)
    return np.stack([c, -s, zero, s, c, zero, zero, zero, one], -1).reshape(-1, 3, 3)


def forward_kinematics(
    model: HandModel, params_deg: np.ndarray, rotation: np.ndarray, centre_mm: np.ndarray
) -> np.ndarray:
    """Camera-frame joints ``(N, 21, 3)`` mm: parameters ``(N, 21)`` deg, rotations ``(N, 3, 3)``,
    palm-centre positions ``(N, 3)`` mm."""
    local = local_pose(model, params_deg) - model.palm_centre
    return np.einsum("nij,nkj->nki", rotation, local) + np.asarray(centre_mm)[:, None, :]


# ---------------------------------------------------------------------------- gestures
def _fingers(*rows: tuple[float, ...]) -> list[float]:
    """Rows (mcp_flex, mcp_abd, pip_flex[, dip_flex]) for index..little; DIP defaults to 2/3 PIP."""
    out: list[float] = []
    for r in rows:
        dip = r[3] if len(r) > 3 else 2.0 / 3.0 * r[2]
        out += [r[0], r[1], r[2], dip]
    return out


_CURLED = (85.0, 0.0, 100.0, 65.0)
_THUMB_ACROSS = [35.0, -30.0, 30.0, 0.0, 45.0]  # thumb folded over the curled fingers
_THUMB_OPEN = [-5.0, 20.0, 5.0, 0.0, 5.0]
_THUMB_IN_PALM = [45.0, -45.0, 45.0, 0.0, 55.0]

#: base gestures: name -> 21 parameters (deg). "pinch" and "ok" get their thumb fitted per hand.
GESTURES: dict[str, list[float]] = {
    "open": _fingers((5, 4, 5), (5, 0, 5), (5, -3, 5), (5, -6, 5)) + _THUMB_OPEN,
    "relaxed": _fingers((12, 3, 18), (16, 0, 24), (20, -3, 30), (26, -5, 36))
    + [15.0, 5.0, 12.0, 0.0, 15.0],
    "spread": _fingers((0, 13, 0), (0, 3, 0), (0, -8, 0), (0, -13, 0))
    + [-15.0, 40.0, 0.0, 0.0, 0.0],
    "fist": _fingers(_CURLED, _CURLED, _CURLED, _CURLED) + _THUMB_ACROSS,
    "point": _fingers((3, 2, 3), _CURLED, _CURLED, _CURLED) + _THUMB_ACROSS,
    "two": _fingers((3, 9, 3), (3, -7, 3), _CURLED, _CURLED) + _THUMB_ACROSS,
    "three": _fingers((3, 9, 3), (3, 0, 3), (5, -8, 5), _CURLED) + _THUMB_IN_PALM,
    "four": _fingers((3, 9, 3), (3, 1, 3), (3, -6, 3), (3, -12, 3)) + _THUMB_IN_PALM,
    "thumbs_up": _fingers(_CURLED, _CURLED, _CURLED, _CURLED) + [5.0, -25.0, 0.0, 0.0, 0.0],
    "claw": _fingers((15, 6, 80, 60), (15, 0, 80, 60), (15, -5, 80, 60), (15, -9, 80, 60))
    + [20.0, 20.0, 20.0, 0.0, 40.0],
    "rock": _fingers((3, 5, 3), _CURLED, _CURLED, (3, -10, 3)) + _THUMB_ACROSS,
    "call": _fingers(_CURLED, _CURLED, _CURLED, (3, -12, 3)) + [-10.0, 35.0, 0.0, 0.0, 0.0],
    "grasp": _fingers((45, 3, 55), (48, 0, 60), (50, -3, 60), (52, -6, 60))
    + [40.0, 0.0, 15.0, 0.0, 20.0],
    "hook": _fingers((0, 3, 95, 60), (0, 0, 95, 60), (0, -3, 95, 60), (0, -6, 95, 60))
    + [0.0, 15.0, 10.0, 0.0, 10.0],
    "pinch": _fingers((35, 0, 40), (30, -2, 45), (35, -5, 55), (40, -8, 60))
    + [30.0, -10.0, 15.0, 0.0, 15.0],
    "ok": _fingers((45, 0, 55, 35), (8, 0, 8), (8, -6, 8), (8, -12, 8))
    + [30.0, -10.0, 15.0, 0.0, 15.0],
}


def _fit_thumb_to_index(model: HandModel, params: np.ndarray, gap_mm: float) -> np.ndarray:
    """Adjust the thumb parameters so the thumb tip is ``gap_mm`` from the index tip.

    Deterministic batched search (a coarse random batch, then two shrinking batches around the best),
    preferring small changes from the given thumb parameters.
    """
    rng = np.random.default_rng(7)
    lo, hi = PARAM_LO[16:], PARAM_HI[16:]
    best = params[16:].copy()
    spread = (hi - lo) / 2.0
    for _ in range(4):
        cand = np.clip(best + rng.uniform(-1, 1, (1500, 5)) * spread, lo, hi)
        cand[0] = best
        batch = np.repeat(params[None], len(cand), axis=0)
        batch[:, 16:] = cand
        pose = local_pose(model, batch)
        d = np.linalg.norm(pose[:, 20] - pose[:, 4], axis=-1)
        cost = (d - gap_mm) ** 2 + 1e-3 * np.sum((cand - params[16:]) ** 2, axis=1)
        best = cand[int(np.argmin(cost))]
        spread = spread / 3.0
    out = params.copy()
    out[16:] = best
    return out


def gesture_library(model: HandModel) -> dict[str, np.ndarray]:
    """Gesture parameters ``(21,)`` deg for a hand (pinch/ok thumbs fitted to its bone lengths)."""
    lib = {
        k: np.clip(np.asarray(v, dtype=np.float64), PARAM_LO, PARAM_HI) for k, v in GESTURES.items()
    }
    lib["pinch"] = _fit_thumb_to_index(model, lib["pinch"], 14.0)
    lib["ok"] = _fit_thumb_to_index(model, lib["ok"], 12.0)
    return lib


# ---------------------------------------------------------------------------- motion
@dataclass
class Keyframe:
    frame: int  # first frame of the hold at this keyframe
    gesture: str
    revisit_of: int  # index of the keyframe it revisits, -1 if new
    hold: int
    transition: int  # frames to the next keyframe
    params: np.ndarray = field(repr=False)  # (21,) deg
    glob: np.ndarray = field(repr=False)  # (6,) yaw, pitch, roll deg; palm centre x, y, z mm


@dataclass
class SynthMotion:
    """The full motion of a synthetic sequence (all frames)."""

    model: HandModel
    params_deg: np.ndarray  # (N, 21)
    yaw_pitch_roll_deg: np.ndarray  # (N, 3)
    centre_mm: np.ndarray  # (N, 3) palm centre, camera frame
    rotation: np.ndarray  # (N, 3, 3)
    joints_mm: np.ndarray  # (N, 21, 3) camera frame
    keyframes: list[Keyframe]


def _ease(n: int) -> np.ndarray:
    """``n`` samples of a cosine ease from 0 (exclusive) to 1 (inclusive)."""
    t = np.arange(1, n + 1) / n
    return 0.5 - 0.5 * np.cos(np.pi * t)


def _sample_glob(rng: np.random.Generator, index: int) -> np.ndarray:
    if index == 0:
        yaw = rng.uniform(-25, 20)  # start palm-facing
    elif index == 1:
        yaw = rng.uniform(150, 195)  # then turn to show the back of the hand
    else:
        yaw = rng.uniform(-70, 200)
    pitch = rng.uniform(-25, 25)
    roll = rng.uniform(-30, 30)
    centre = (rng.uniform(-35, 35), rng.uniform(-25, 30), rng.uniform(350, 400))
    return np.array([yaw, pitch, roll, *centre])


def _segment(
    a: Keyframe, b_params: np.ndarray, b_glob: np.ndarray, n: int
) -> tuple[np.ndarray, np.ndarray]:
    s = _ease(n)[:, None]
    return a.params + s * (b_params - a.params), a.glob + s * (b_glob - a.glob)


def _max_step_mm(model: HandModel, params: np.ndarray, glob: np.ndarray) -> float:
    joints = forward_kinematics(model, params, rotation_matrices(glob[:, :3]), glob[:, 3:])
    return float(np.linalg.norm(np.diff(joints, axis=0), axis=-1).max())


def _transition_frames(rng, model, current, params, glob, speed_mm) -> int:
    """Frames of the transition from keyframe ``current`` to ``params``/``glob``, timed for a
    target peak joint speed (mm/frame) drawn from ``rng`` (see :func:`synthesize_motion`)."""
    if speed_mm is None:
        speed = rng.uniform(9.0, 10.0) if rng.random() < 0.12 else rng.uniform(2.5, 6.0)
    else:
        speed = rng.uniform(*speed_mm)
    probe = 60
    p_probe, g_probe = _segment(current, params, glob, probe)
    p_probe = np.concatenate([current.params[None], p_probe])
    g_probe = np.concatenate([current.glob[None], g_probe])
    step = _max_step_mm(model, p_probe, g_probe)
    return max(6 if speed_mm is None else 3, int(np.ceil(probe * step / speed)))


def _tremor(seed: int, frames: int) -> tuple[np.ndarray, np.ndarray]:
    """Smooth tremor ``(frames, NUM_PARAMS)`` deg and ``(frames, 6)`` (rotation deg, mm): a few
    slow sinusoids per parameter (own RNG: a shorter sequence's tremor is a prefix)."""
    rng = np.random.default_rng([seed, 303])
    t = np.arange(frames)[:, None]
    tremor_p = np.zeros((frames, NUM_PARAMS))
    tremor_g = np.zeros((frames, 6))
    for _ in range(3):
        period = rng.uniform(25, 90, NUM_PARAMS + 6)
        phase = rng.uniform(0, 2 * np.pi, NUM_PARAMS + 6)
        wave = np.sin(2 * np.pi * t / period + phase)
        tremor_p += 0.6 * wave[:, :NUM_PARAMS]
        tremor_g += np.array([0.5, 0.5, 0.5, 0.6, 0.6, 0.6]) * wave[:, NUM_PARAMS:]
    return tremor_p, tremor_g


def synthesize_motion(
    frames: int,
    seed: int = 0,
    *,
    model: HandModel | None = None,
    speed_mm: tuple[float, float] | None = None,
    hold_frames: tuple[int, int] = (0, 40),
) -> SynthMotion:
    """Generate the motion (articulation + global pose) of a ``frames``-long sequence.

    Keyframes pick a gesture (random, never the same twice in a row) with a few degrees of
    variation and a global pose; about 30 % of keyframes after the sixth revisit an earlier
    keyframe (same gesture, similar global pose). Each keyframe is held 0-40 frames, and the
    transition to the next one is timed so that the fastest joint moves at a target peak speed of
    2.5-6 mm/frame (about 1 in 8 transitions is fast: 9-10 mm/frame). A small smooth tremor
    (about 1 degree, 1 mm) runs throughout.

    ``model`` replaces the per-seed hand of :func:`make_hand_model`; ``speed_mm`` (low, high)
    replaces the peak-speed mix with one uniform range (fast motion: transitions of 3 or more
    frames); ``hold_frames`` (low, high) bounds the holds after the first keyframe.
    """
    if frames < 1:
        raise ValueError("frames must be >= 1")
    rng = np.random.default_rng([seed, 202])
    model = make_hand_model(seed) if model is None else model
    lib = gesture_library(model)
    names = sorted(lib)
    keyframes: list[Keyframe] = []
    params_parts: list[np.ndarray] = []
    glob_parts: list[np.ndarray] = []
    total = 0

    def new_keyframe(index: int, previous: str | None) -> tuple[str, int, np.ndarray, np.ndarray]:
        distinct = [i for i, k in enumerate(keyframes) if k.revisit_of < 0]
        if index >= 6 and rng.random() < 0.3:
            j = int(rng.choice([i for i in distinct if keyframes[i].gesture != previous]))
            src = keyframes[j]
            params = np.clip(src.params + rng.normal(0, 2.0, NUM_PARAMS), PARAM_LO, PARAM_HI)
            glob = src.glob + np.concatenate([rng.normal(0, 4.0, 3), rng.normal(0, 4.0, 3)])
            return src.gesture, j, params, glob
        if index == 0:
            name = "open"
        else:
            name = str(rng.choice([g for g in names if g != previous]))
        params = np.clip(lib[name] + rng.normal(0, 3.0, NUM_PARAMS), PARAM_LO, PARAM_HI)
        return name, -1, params, _sample_glob(rng, index)

    name, rev, params, glob = new_keyframe(0, None)
    current = Keyframe(0, name, rev, 0, 0, params, glob)
    while True:
        if keyframes:
            hold = int(rng.integers(hold_frames[0], hold_frames[1] + 1))
        else:
            hold = int(rng.integers(0, min(8, hold_frames[1] + 1)))
        current.hold = hold
        current.frame = total
        keyframes.append(current)
        params_parts.append(np.repeat(current.params[None], hold, axis=0))
        glob_parts.append(np.repeat(current.glob[None], hold, axis=0))
        total += hold
        if total >= frames:
            break
        name, rev, params, glob = new_keyframe(len(keyframes), current.gesture)
        n = _transition_frames(rng, model, current, params, glob, speed_mm)
        current.transition = n
        p_seg, g_seg = _segment(current, params, glob, n)
        params_parts.append(p_seg)
        glob_parts.append(g_seg)
        total += n
        current = Keyframe(total, name, rev, 0, 0, params, glob)
        if total >= frames:
            current.frame = total
            keyframes.append(current)
            break

    params_all = np.concatenate(params_parts)[:frames]
    glob_all = np.concatenate(glob_parts)[:frames]
    tremor_p, tremor_g = _tremor(seed, frames)
    params_all = np.clip(params_all + tremor_p, PARAM_LO, PARAM_HI)
    glob_all = glob_all + tremor_g
    rotation = rotation_matrices(glob_all[:, :3])
    joints = forward_kinematics(model, params_all, rotation, glob_all[:, 3:])
    keyframes = [k for k in keyframes if k.frame < frames]
    return SynthMotion(
        model, params_all, glob_all[:, :3], glob_all[:, 3:], rotation, joints, keyframes
    )


# ---------------------------------------------------------------------------- geometry
@dataclass
class Primitives:
    """Solids in the camera frame (mm): capsules (segment ``a``-``b``, radius) and ellipsoids."""

    cap_a: np.ndarray  # (P, 3)
    cap_b: np.ndarray  # (P, 3)
    cap_r: np.ndarray  # (P,)
    ell_c: np.ndarray  # (E, 3) centres
    ell_axes: np.ndarray  # (E, 3, 3) columns = unit axes
    ell_s: np.ndarray  # (E, 3) semi-axes


def hand_primitives(
    model: HandModel,
    joints_mm: np.ndarray,
    rotation: np.ndarray,
    forearm_dir: np.ndarray | None = None,
    *,
    forearm_length_mm: float = _FOREARM_LENGTH,
    sleeve: bool = False,
) -> Primitives:
    """Capsules and ellipsoids of the hand, palm and forearm for one frame.

    ``joints_mm`` ``(21, 3)`` camera frame, ``rotation`` ``(3, 3)`` local-to-camera.
    ``forearm_dir`` ``(3,)``: unit direction from the wrist towards the elbow in the camera frame;
    None = along the hand's own axis (local ``-y``, a straight wrist). The forearm runs
    ``forearm_length_mm`` from the wrist but stops before it reaches :data:`NEAR_CLIP_MM` of the
    camera (an arm pointing at the camera); ``sleeve`` adds a wider round sleeve over its upper part.
    """
    j = np.asarray(joints_mm, dtype=np.float64)
    r_mat = np.asarray(rotation, dtype=np.float64)
    wrist = j[0]
    x_ax, y_ax, z_ax = r_mat[:, 0], r_mat[:, 1], r_mat[:, 2]
    thick = model.palm_half_thickness_mm
    a, b, r = [], [], []
    for f, chain in enumerate(_CHAINS):
        for k in range(3):
            p0, p1 = j[chain[k]], j[chain[k + 1]]
            rad = model.finger_radii[f, k]
            if k == 2:  # distal bone: cap reaches the tip
                d = p1 - p0
                length = np.linalg.norm(d)
                p1 = p0 + d * max(length - rad, 0.5) / max(length, 1e-9)
            a.append(p0)
            b.append(p1)
            r.append(rad)
    mcps = j[[1, 5, 9, 13]]
    palm_r = thick - 1.5
    # metacarpals (palm body), knuckle line, heel of the hand, thenar (wrist to thumb CMC/MCP)
    for m in mcps:
        a.append(wrist + 0.25 * (m - wrist))
        b.append(m)
        r.append(palm_r)
    a += [mcps[0], mcps[1], mcps[2]]
    b += [mcps[1], mcps[2], mcps[3]]
    r += [palm_r + 0.5] * 3
    a.append(wrist + 14.0 * x_ax + 6.0 * y_ax)
    b.append(wrist - 14.0 * x_ax + 6.0 * y_ax)
    r.append(thick + 1.0)
    a.append(wrist + 8.0 * x_ax + 8.0 * y_ax)
    b.append(j[17])
    r.append(thick + 1.5)
    # forearm: two side-by-side capsules give the flattened cross-section of a real distal forearm
    # (about 60 mm wide, 44 mm thick) instead of a round 52 mm tube
    arm = -y_ax if forearm_dir is None else _unit(np.asarray(forearm_dir, dtype=np.float64))
    side_ax = _unit(x_ax - (x_ax @ arm) * arm)
    start, end = 18.0, _clipped_length(wrist, arm, forearm_length_mm, model.forearm_radius_mm)
    if end > start:
        for side in (-1.0, 1.0):
            a.append(wrist + start * arm + side * _FOREARM_SPREAD * side_ax)
            b.append(wrist + end * arm + side * _FOREARM_SPREAD * side_ax)
            r.append(model.forearm_radius_mm)
    if sleeve and end > _SLEEVE_START_MM:
        a.append(wrist + _SLEEVE_START_MM * arm)
        b.append(wrist + end * arm)
        r.append(model.forearm_radius_mm + _FOREARM_SPREAD + _SLEEVE_EXTRA_MM)
    # palm slab: ellipsoid over wrist..MCPs
    centre_local = np.array([0.0, 0.55 * model.local_base[[1, 5, 9, 13], 1].mean(), 0.0])
    half_width = 0.5 * (model.local_base[1, 0] - model.local_base[13, 0]) + 8.0
    half_len = 0.5 * model.local_base[[1, 5, 9, 13], 1].mean()
    wrist_local = model.local_base[0]
    centre = wrist + r_mat @ (centre_local - wrist_local)
    return Primitives(
        cap_a=np.asarray(a),
        cap_b=np.asarray(b),
        cap_r=np.asarray(r),
        ell_c=centre[None],
        ell_axes=np.stack([x_ax, y_ax, z_ax], axis=1)[None],
        ell_s=np.array([[half_width, half_len, thick]]),
    )


def _clipped_length(
    origin: np.ndarray, direction: np.ndarray, length: float, radius: float
) -> float:
    """``length`` shortened so the capsule ``origin + t * direction`` (t <= length) stays
    :data:`NEAR_CLIP_MM` plus ``radius`` in front of the camera (z)."""
    if direction[2] >= 0:
        return length
    room = (origin[2] - NEAR_CLIP_MM - radius) / -direction[2]
    return float(min(length, max(room, 0.0)))


_RAY_CACHE: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}


def _rays(camera: CameraIntrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Unit ray directions ``(H, W, 3)`` through pixel centres and their z components ``(H, W)``."""
    key = (camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height)
    if key not in _RAY_CACHE:
        u, v = np.meshgrid(np.arange(camera.width), np.arange(camera.height))
        d = np.stack(
            [(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones(u.shape)], axis=-1
        )
        d = _unit(d)
        _RAY_CACHE[key] = (d, d[..., 2].copy())
    return _RAY_CACHE[key]


def _bbox(
    points: np.ndarray, radius: float, camera: CameraIntrinsics
) -> tuple[int, int, int, int] | None:
    """Conservative pixel box ``(u0, u1, v0, v1)`` (exclusive ends) of spheres around points."""
    z = points[:, 2]
    if np.any(z <= radius + 1.0):
        return 0, camera.width, 0, camera.height
    uv = camera.project(points)
    pad = radius * max(camera.fx, camera.fy) / (z.min() - radius) + 2.0
    u0 = max(int(np.floor(uv[:, 0].min() - pad)), 0)
    u1 = min(int(np.ceil(uv[:, 0].max() + pad)) + 1, camera.width)
    v0 = max(int(np.floor(uv[:, 1].min() - pad)), 0)
    v1 = min(int(np.ceil(uv[:, 1].max() + pad)) + 1, camera.height)
    if u0 >= u1 or v0 >= v1:
        return None
    return u0, u1, v0, v1


def render_depth(prims: Primitives, camera: CameraIntrinsics) -> np.ndarray:
    """Exact ray-cast depth ``(H, W)`` float32 mm (z of the nearest hit; 0 = no hit).

    Each solid is intersected only with the rays in its projected bounding box.
    """
    rays, rz = _rays(camera)
    zbuf = np.full((camera.height, camera.width), np.inf)
    for pa, pb, rad in zip(prims.cap_a, prims.cap_b, prims.cap_r, strict=True):
        box = _bbox(np.stack([pa, pb]), rad, camera)
        if box is None:
            continue
        u0, u1, v0, v1 = box
        rd = rays[v0:v1, u0:u1]
        ba = pb - pa
        oa = -pa
        baba = ba @ ba
        bard = rd @ ba
        baoa = ba @ oa
        rdoa = rd @ oa
        oaoa = oa @ oa
        qa = np.maximum(baba - bard * bard, 1e-12)
        qb = baba * rdoa - baoa * bard
        qc = baba * oaoa - baoa * baoa - rad * rad * baba
        h = qb * qb - qa * qc
        hit = h >= 0
        sq = np.sqrt(np.where(hit, h, 0.0))
        t = (-qb - sq) / qa
        y = baoa + t * bard
        on_body = hit & (y > 0) & (y < baba)
        # caps: the sphere at the end the cylinder entry lies beyond
        oc = np.where((y <= 0)[..., None], oa, -pb)
        sb = np.sum(rd * oc, axis=-1)
        sc = np.sum(oc * oc, axis=-1) - rad * rad
        sh = sb * sb - sc
        cap_hit = hit & ~on_body & (sh > 0)
        t_cap = -sb - np.sqrt(np.where(cap_hit, sh, 0.0))
        t = np.where(on_body, t, np.where(cap_hit, t_cap, np.inf))
        t = np.where(t > 0, t, np.inf)
        region = zbuf[v0:v1, u0:u1]
        np.minimum(region, t * rz[v0:v1, u0:u1], out=region)
    for c, axes, s in zip(prims.ell_c, prims.ell_axes, prims.ell_s, strict=True):
        corners = (
            c[:, None]
            + (axes * s)
            @ np.array(
                [[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], dtype=np.float64
            ).T
        )
        box = _bbox(corners.T, 0.0, camera)
        if box is None:
            continue
        u0, u1, v0, v1 = box
        rd = rays[v0:v1, u0:u1]
        o = (axes.T @ (-c)) / s
        d = (rd @ axes) / s
        qa = np.sum(d * d, axis=-1)
        qb = d @ o
        qc = o @ o - 1.0
        h = qb * qb - qa * qc
        hit = h >= 0
        t = (-qb - np.sqrt(np.where(hit, h, 0.0))) / qa
        t = np.where(hit & (t > 0), t, np.inf)
        region = zbuf[v0:v1, u0:u1]
        np.minimum(region, t * rz[v0:v1, u0:u1], out=region)
    return np.where(np.isfinite(zbuf), zbuf, 0.0).astype(np.float32)


def add_sensor_noise(
    depth: np.ndarray,
    rng: np.random.Generator,
    *,
    sigma_mm: float = 1.0,
    edge_jump_mm: float = 20.0,
    edge_dropout: float = 0.45,
    holes: float = 2.0,
    hole_radius_px: tuple[float, float] = (1.0, 3.0),
) -> np.ndarray:
    """Sensor-like corruption of a clean depth map ``(H, W)`` float32 mm (0 = background).

    Gaussian noise (``sigma_mm``); a random ``edge_dropout`` fraction of the pixels whose depth
    differs by more than ``edge_jump_mm`` from a 4-neighbour (silhouette and self-occlusion edges)
    set to 0; a Poisson(``holes``) number of small round holes (radius ``hole_radius_px``) on the hand.
    """
    full = np.asarray(depth, dtype=np.float32)
    result = np.zeros_like(full)
    rows_any = np.flatnonzero(full.any(axis=1))
    if rows_any.size == 0:
        return result
    cols_any = np.flatnonzero(full.any(axis=0))
    # work on the hand's bounding box (plus a margin for the holes), not the whole image
    reach = int(np.ceil(hole_radius_px[1]))
    r0, r1 = max(rows_any[0] - 1, 0), min(rows_any[-1] + 2, full.shape[0])
    c0, c1 = max(cols_any[0] - 1, 0), min(cols_any[-1] + 2, full.shape[1])
    clean = full[r0:r1, c0:c1]
    valid = clean > 0
    out = clean + rng.normal(0.0, sigma_mm, clean.shape).astype(np.float32)
    pad = np.pad(clean, 1)
    centre = pad[1:-1, 1:-1]
    jump = np.zeros(clean.shape, dtype=bool)
    for nb in (pad[:-2, 1:-1], pad[2:, 1:-1], pad[1:-1, :-2], pad[1:-1, 2:]):
        jump |= np.abs(centre - nb) > edge_jump_mm
    drop = valid & jump & (rng.random(clean.shape) < edge_dropout)
    keep = valid & ~drop
    rows, cols = np.nonzero(valid)
    n_holes = int(rng.poisson(holes))
    if n_holes:
        picks = rng.integers(0, rows.size, n_holes)
        radii = rng.uniform(hole_radius_px[0], hole_radius_px[1], n_holes)
        vv, uu = np.mgrid[-reach : reach + 1, -reach : reach + 1]
        for p, rad in zip(picks, radii, strict=True):
            disk = vv**2 + uu**2 <= rad**2
            rr = np.clip(rows[p] + vv[disk], 0, clean.shape[0] - 1)
            cc = np.clip(cols[p] + uu[disk], 0, clean.shape[1] - 1)
            keep[rr, cc] = False
    result[r0:r1, c0:c1] = np.where(keep, np.maximum(out, 1.0), 0.0)
    return result


@dataclass(frozen=True)
class SensorModel:
    """How a depth sensor corrupts the exact depth (all lengths mm, all fractions 0-1).

    Applied in this order to the clean ray-cast map: :func:`add_sensor_noise` (Gaussian noise
    ``sigma_mm``, dropout at depth discontinuities, round holes), depth-dependent noise
    ``sigma_z2 * z**2``, quantization of the disparity ``disparity_fb / z`` (focal length x baseline,
    px mm) in steps of ``disparity_step_px``, extra noise ``edge_noise_mm`` on pixels within one pixel
    of a discontinuity, flying pixels (a ``flying`` fraction of the pixels just outside the silhouette
    get a depth ``flying_behind_mm`` behind their neighbour; the same fraction of the pixels on the far
    side of an inner discontinuity get a depth between the two surfaces), and no measurement closer
    than ``min_range_mm``. The default is the corruption of ``handanno synth`` (MSRA-like).
    """

    name: str = "msra"
    sigma_mm: float = 1.0
    edge_jump_mm: float = 20.0
    edge_dropout: float = 0.45
    holes: float = 2.0
    hole_radius_px: tuple[float, float] = (1.0, 3.0)
    sigma_z2: float = 0.0
    disparity_fb: float = 0.0
    disparity_step_px: float = 0.125
    edge_noise_mm: float = 0.0
    flying: float = 0.0
    flying_behind_mm: tuple[float, float] = (10.0, 150.0)
    min_range_mm: float = 0.0

    def apply(self, depth: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Corrupt a clean depth map ``(H, W)`` float32 mm (0 = no hit); returns a new map."""
        out = add_sensor_noise(
            depth,
            rng,
            sigma_mm=self.sigma_mm,
            edge_jump_mm=self.edge_jump_mm,
            edge_dropout=self.edge_dropout,
            holes=self.holes,
            hole_radius_px=self.hole_radius_px,
        )
        if self == SensorModel(name=self.name):
            return out
        clean = np.asarray(depth, dtype=np.float32)
        valid = out > 0
        if self.sigma_z2 > 0:
            out = out + valid * rng.normal(0.0, 1.0, out.shape) * self.sigma_z2 * out**2
        pad = np.pad(clean, 1)
        neighbours = (pad[:-2, 1:-1], pad[2:, 1:-1], pad[1:-1, :-2], pad[1:-1, 2:])
        jump = np.zeros(clean.shape, dtype=bool)
        for nb in neighbours:
            jump |= np.abs(clean - nb) > self.edge_jump_mm
        if self.edge_noise_mm > 0:
            out = out + (valid & jump) * rng.normal(0.0, self.edge_noise_mm, out.shape)
        if self.flying > 0:
            near = np.zeros_like(clean)  # the nearest 4-neighbour's depth (0 where none)
            for nb in neighbours:
                near = np.where((nb > 0) & ((near == 0) | (nb < near)), nb, near)
            outside = (clean == 0) & (near > 0) & (rng.random(clean.shape) < self.flying)
            lo, hi = self.flying_behind_mm
            out = np.where(outside, near + rng.uniform(lo, hi, clean.shape), out)
            inner = valid & jump & (near > 0) & (near < clean - self.edge_jump_mm)
            inner &= rng.random(clean.shape) < self.flying
            mix = rng.uniform(0.2, 0.8, clean.shape)
            out = np.where(inner, clean + mix * (near - clean), out)
        valid = out > 0
        if self.disparity_fb > 0:
            step = self.disparity_step_px
            disparity = np.round(self.disparity_fb / np.where(valid, out, 1.0) / step) * step
            out = np.where(valid, self.disparity_fb / np.maximum(disparity, step), 0.0)
        out = np.where(out >= max(self.min_range_mm, 1.0), out, 0.0)
        return out.astype(np.float32)


#: today's ``handanno synth`` corruption (MSRA-like, 320x240)
MSRA_SENSOR = SensorModel()
#: Kinect v1 (structured light): disparity quantized to 1/8 px with f x b = 580 px x 75 mm, noise
#: growing with z**2 (Khoshelham & Elberink, Sensors 2012, 12(2):1437-1454: sigma ~1.4 mm at 1 m),
#: flying pixels at silhouettes and inner edges, a 400 mm minimum range
KINECT_SENSOR = SensorModel(
    name="kinect",
    sigma_mm=0.5,
    edge_dropout=0.25,
    holes=1.0,
    sigma_z2=1.4e-6,
    disparity_fb=580.0 * 75.0,
    flying=0.5,
    min_range_mm=400.0,
)
#: Intel SR300 (coded light, short range): larger and more frequent holes, ragged noisy edges
SR300_SENSOR = SensorModel(
    name="sr300",
    sigma_mm=1.2,
    edge_dropout=0.65,
    holes=6.0,
    hole_radius_px=(2.0, 6.0),
    edge_noise_mm=6.0,
    flying=0.15,
    flying_behind_mm=(5.0, 40.0),
    min_range_mm=150.0,
)
SENSORS: dict[str, SensorModel] = {s.name: s for s in (MSRA_SENSOR, KINECT_SENSOR, SR300_SENSOR)}


def render_frame(
    model: HandModel,
    joints_mm: np.ndarray,
    rotation: np.ndarray,
    camera: CameraIntrinsics = MSRA_CAMERA,
    *,
    noise_seed: tuple[int, int] | None = None,
    forearm_dir: np.ndarray | None = None,
    sleeve: bool = False,
    sensor: SensorModel = MSRA_SENSOR,
) -> np.ndarray:
    """Depth ``(H, W)`` float32 mm of one hand pose; ``noise_seed=(seed, frame)`` adds ``sensor``'s
    corruption. ``forearm_dir`` ``(3,)`` (wrist towards elbow, camera frame; None = straight wrist)
    draws an :data:`ARM_LENGTH_MM` arm at that angle; ``sleeve`` covers its upper part."""
    length = _FOREARM_LENGTH if forearm_dir is None else ARM_LENGTH_MM
    prims = hand_primitives(
        model, joints_mm, rotation, forearm_dir, forearm_length_mm=length, sleeve=sleeve
    )
    depth = render_depth(prims, camera)
    if noise_seed is not None:
        depth = sensor.apply(depth, np.random.default_rng([noise_seed[0], noise_seed[1], 303]))
    return depth


#: how the forearm is posed: ``hand`` = along the hand (straight wrist, today's sequences),
#: ``wrist`` = wrist flexion/extension and deviation over their range of motion, ``top-down`` = the
#: arm in the image plane turning through every direction (a camera above a table),
#: ``egocentric`` = the elbow nearer to the camera than the hand and below it (head-mounted camera)
ARM_MODES = ("hand", "wrist", "top-down", "egocentric")


def _smooth_wave(n: int, rng: np.random.Generator, count: int) -> np.ndarray:
    """``(n, count)`` smooth signals in [-1, 1]: two slow sinusoids each (periods 60-240 frames)."""
    t = np.arange(n)[:, None]
    out = np.zeros((n, count))
    for _ in range(2):
        period = rng.uniform(60, 240, count)
        out += 0.5 * np.sin(2 * np.pi * t / period + rng.uniform(0, 2 * np.pi, count))
    return out


def pose_arm(
    joints_mm: np.ndarray, rotation: np.ndarray, mode: str, seed: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """The hand and its forearm for an :data:`ARM_MODES` mode: ``(joints_mm, rotation, forearm)``.

    ``joints_mm`` ``(N, 21, 3)``, ``rotation`` ``(N, 3, 3)`` local-to-camera (the hand's local
    ``-y`` is its forearm's natural direction, wrist straight); ``forearm`` ``(N, 3)`` unit
    wrist-to-elbow directions in the camera frame (None for ``hand``).

    * ``wrist``: flexion -60..+70 deg and deviation -25..+30 deg of the wrist (its range of motion,
      about 70/80 and 20/30 deg), so with the hand's own rotation the arm takes every direction,
      towards the camera included; the hand is returned as given.
    * ``top-down``: the arm turns once through every in-plane direction every 240 frames, the
      elbow 5-25 deg farther than the wrist, and the hand turns with it about the camera's axis
      through its centre (the mean of its joints, so it stays in view), its natural forearm
      direction within the wrist's deviation (-25..+30 deg) of the arm in the image. Before stop
      41 the hand did not turn and the arm could run through its fingers, which no wrist allows
      (benchmarks/HISTORY.md).
    * ``egocentric``: the elbow 100-200 mm nearer than the wrist and 60-180 mm below it in the
      image, whatever the hand's orientation (the hand is returned as given), so the arm can
      leave the wrist a little beyond its range of motion.
    """
    if mode not in ARM_MODES:
        raise ValueError(f"unknown arm mode {mode!r}; known: {', '.join(ARM_MODES)}")
    joints_mm, rotation = np.asarray(joints_mm, float), np.asarray(rotation, float)
    if mode == "hand":
        return joints_mm, rotation, None
    n = len(joints_mm)
    rng = np.random.default_rng([seed, 505])
    w = _smooth_wave(n, rng, 3)
    if mode == "wrist":
        flex = np.radians(5.0 + 65.0 * w[:, 0])
        dev = np.radians(2.5 + 27.5 * w[:, 1])
        local = np.stack(
            [np.sin(dev), -np.cos(dev) * np.cos(flex), np.cos(dev) * np.sin(flex)], axis=-1
        )
        return joints_mm, rotation, np.einsum("nij,nj->ni", rotation, local)
    if mode == "top-down":
        theta = rng.uniform(0, 2 * np.pi) + 2 * np.pi * np.arange(n) / 240.0 + 0.3 * w[:, 0]
        tilt = np.radians(15.0 + 10.0 * w[:, 1])
        arm = np.stack(
            [np.cos(theta) * np.cos(tilt), np.sin(theta) * np.cos(tilt), np.sin(tilt)], axis=-1
        )
        # turn the hand so that its natural forearm direction points where the arm does, give or
        # take the wrist's deviation; smoothed over a few frames (causally: a shorter sequence
        # stays a prefix of a longer one), since the image azimuth of a hand pointing along the
        # camera's axis is ill-defined
        natural = -rotation[:, :, 1]
        deviation = np.radians(2.5 + 27.5 * w[:, 2])
        target = np.unwrap(theta - deviation - np.arctan2(natural[:, 1], natural[:, 0]))
        turn = np.empty(n)
        turn[0] = target[0]
        for i in range(1, n):
            turn[i] = turn[i - 1] + 0.5 * (target[i] - turn[i - 1])
        rz = _rotation_z(turn)
        centre = joints_mm.mean(axis=1, keepdims=True)  # the hand stays where the camera sees it
        joints_mm = np.einsum("nij,nkj->nki", rz, joints_mm - centre) + centre
        return joints_mm, rz @ rotation, arm
    offset = np.stack([60.0 * w[:, 0], 120.0 + 60.0 * w[:, 1], -(150.0 + 50.0 * w[:, 2])], -1)
    return joints_mm, rotation, _unit(offset)


# ---------------------------------------------------------------------------- sequence writer
def _render_chunk(
    out_dir: str,
    frames: np.ndarray,
    joints: np.ndarray,
    rotation: np.ndarray,
    model: HandModel,
    seed: int,
    camera_json: str,
    forearm: np.ndarray | None = None,
    sleeve: bool = False,
    sensor: SensorModel = MSRA_SENSOR,
) -> int:
    from .datasets.msra import write_msra_frame

    camera = CameraIntrinsics.model_validate_json(camera_json)
    for i, f in enumerate(frames):
        depth = render_frame(
            model,
            joints[i],
            rotation[i],
            camera,
            noise_seed=(seed, int(f)),
            forearm_dir=None if forearm is None else forearm[i],
            sleeve=sleeve,
            sensor=sensor,
        )
        write_msra_frame(os.path.join(out_dir, f"{int(f):06d}_depth.bin"), depth)
    return len(frames)


def write_sequence(
    out_dir: str | Path,
    model: HandModel,
    joints_mm: np.ndarray,
    rotation: np.ndarray,
    *,
    seed: int = 0,
    camera: CameraIntrinsics = MSRA_CAMERA,
    sensor: SensorModel = MSRA_SENSOR,
    forearm: np.ndarray | None = None,
    sleeve: bool = False,
    info: dict | None = None,
    progress: bool = True,
    workers: int = 2,
) -> Path:
    """Render given joints into ``out_dir``: MSRA layout, ``camera.json`` and ``synth.json`` (``info``).

    ``joints_mm`` ``(N, 21, 3)`` camera frame, ``rotation`` ``(N, 3, 3)`` local-to-camera (palm and
    wrist orientation), ``forearm`` ``(N, 3)`` wrist-to-elbow directions or None (straight wrist).
    Every frame's noise has its own RNG (``seed``, frame), so the output does not depend on
    ``workers``. Frame files numbered ``>= N`` left by an earlier run are deleted.
    """
    from .datasets.msra import write_msra_joints

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    frames = len(joints_mm)
    # frames left over from an earlier, longer sequence in the same folder would be read back
    for stale in out.glob("*_depth.bin"):
        stem = stale.name[: -len("_depth.bin")]
        if stem.isdigit() and int(stem) >= frames:
            stale.unlink()
    camera.to_json(out / "camera.json")
    write_msra_joints(out / "joint.txt", joints_mm)
    (out / "synth.json").write_text(json.dumps(info or {}, indent=1))

    chunk = 40
    jobs = [
        (
            str(out),
            np.arange(s, min(s + chunk, frames)),
            joints_mm[s : s + chunk],
            rotation[s : s + chunk],
            model,
            seed,
            camera.model_dump_json(),
            None if forearm is None else forearm[s : s + chunk],
            sleeve,
            sensor,
        )
        for s in range(0, frames, chunk)
    ]
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=frames, desc=f"synth {out.name}", unit="frame", leave=True)
    try:
        if workers <= 1 or len(jobs) == 1:
            for job in jobs:
                done = _render_chunk(*job)
                if bar is not None:
                    bar.update(done)
        else:
            with ProcessPoolExecutor(max_workers=workers, mp_context=get_context("spawn")) as pool:
                futures = [pool.submit(_render_chunk, *job) for job in jobs]
                for fut in futures:
                    done = fut.result()
                    if bar is not None:
                        bar.update(done)
    finally:
        if bar is not None:
            bar.close()
    return out


def generate_sequence(
    out_dir: str | Path,
    frames: int = 3040,
    seed: int = 0,
    progress: bool = True,
    workers: int = 2,
    *,
    arm: str = "hand",
    sleeve: bool = False,
) -> Path:
    """Render a synthetic sequence into ``out_dir`` (MSRA layout + ``camera.json`` + ``synth.json``).

    Deterministic for a given ``seed`` whatever ``workers`` (every frame's noise has its own RNG),
    and a shorter sequence is a prefix of a longer one with the same seed. Frame files numbered
    ``>= frames`` left in ``out_dir`` by an earlier run are deleted.
    ``arm`` (one of :data:`ARM_MODES`) poses the forearm (default: along the hand, today's
    sequences); ``sleeve`` adds a sleeve over it.
    ``workers`` processes render chunks of frames; ``progress`` shows a one-line tqdm bar.
    Returns ``out_dir`` as a Path.
    """
    motion = synthesize_motion(frames, seed)
    joints, rotation, forearm = pose_arm(motion.joints_mm, motion.rotation, arm, seed)
    info = describe_motion(motion, seed)
    if arm != "hand" or sleeve:
        # a top-down arm turns the hand with it: the motion summary is of the hand before the turn
        info["arm"] = {"mode": arm, "sleeve": sleeve, "hand_turned": arm == "top-down"}
    return write_sequence(
        out_dir,
        motion.model,
        joints,
        rotation,
        seed=seed,
        forearm=forearm,
        sleeve=sleeve,
        info=info,
        progress=progress,
        workers=workers,
    )


def describe_motion(motion: SynthMotion, seed: int) -> dict:
    """JSON-able summary: seed, bone lengths, the keyframe schedule, yaw and depth ranges."""
    normal_z = MSRA21.palm_normal(motion.joints_mm)[:, 2]
    return {
        "seed": seed,
        "frames": len(motion.joints_mm),
        "bone_lengths_mm": [round(float(x), 3) for x in motion.model.bone_lengths_mm],
        "yaw_range_deg": [
            float(motion.yaw_pitch_roll_deg[:, 0].min()),
            float(motion.yaw_pitch_roll_deg[:, 0].max()),
        ],
        "palm_facing_fraction": float(np.mean(normal_z < 0)),
        "joint_depth_range_mm": [
            float(motion.joints_mm[..., 2].min()),
            float(motion.joints_mm[..., 2].max()),
        ],
        "keyframes": [
            {
                "frame": k.frame,
                "gesture": k.gesture,
                "revisit_of": k.revisit_of,
                "hold": k.hold,
                "transition": k.transition,
                "yaw_pitch_roll_deg": [round(float(x), 2) for x in k.glob[:3]],
                "centre_mm": [round(float(x), 2) for x in k.glob[3:]],
            }
            for k in motion.keyframes
        ],
    }


# ---------------------------------------------------------------------------- template hand
def template_hand(skeleton: Skeleton, centre_mm: np.ndarray) -> np.ndarray | None:
    """``(J, 3)`` mm: a relaxed hand of the skeleton's template bone lengths, palm facing the
    camera, fingers up, the joints' mean at ``centre_mm`` (3,) mm: the first guess of a frame when
    nothing in the session has joints yet (instead of joints hung off the wrist in a column).
    None for skeletons other than MSRA21's layout (the hand model is written for it)."""
    if skeleton.joint_names != MSRA21.joint_names or skeleton.template_bone_lengths_mm is None:
        return None
    hand = _relaxed_hand(tuple(float(x) for x in skeleton.template_bone_lengths_mm))
    return hand + np.asarray(centre_mm, dtype=np.float64)


@functools.lru_cache(maxsize=8)
def _relaxed_hand(bone_lengths_mm: tuple[float, ...]) -> np.ndarray:
    """:func:`template_hand`'s hand with its joints' mean at 0 (built once per bone lengths: the
    lift asks for it on every frame with unplaced joints)."""
    model = build_hand_model(np.asarray(bone_lengths_mm, dtype=np.float64))
    params = np.asarray(GESTURES["relaxed"], dtype=np.float64)[None]
    hand = forward_kinematics(model, params, rotation_matrices(np.zeros((1, 3))), np.zeros((1, 3)))
    out = hand[0] - hand[0].mean(axis=0)
    out.flags.writeable = False
    return out


# ---------------------------------------------------------------------------- simulated annotator
def simulate_annotation(
    gt_joints_mm: np.ndarray,
    depth: np.ndarray,
    camera: CameraIntrinsics,
    skeleton: Skeleton = MSRA21,
    noise_px: float = 0.0,
    rng: np.random.Generator | None = None,
) -> FrameAnnotation:
    """What a careful annotator would click for one frame, from ground truth (benchmarks only).

    * ``uv_px``: projection of the ground-truth joints ``(J, 3)`` plus Gaussian noise of std
      ``noise_px`` per coordinate, kept on the image (a click lands on it); NaN (not annotated)
      for a joint whose true projection is off the image, which nobody can click (the app's
      clicks and accepted guesses land on the image); such a joint is marked ``outside`` (the
      app's "Outside the image"), which the lift places by its constraints;
    * ``visible``: :func:`sampling.visible_by_depth` of the ground truth (the closest valid depth
      ``D`` in the 3x3 pixels at the rounded projection satisfies ``D >= z - surface_offset - 10 mm``;
      no valid depth there, or off the image -> False);
    * ``depth_order``: +1 if ``z > z_parent + 10 mm``, -1 if ``z < z_parent - 10 mm``, else 0 (root 0;
      0 for a joint off the image);
    * ``xyz_mm``: all NaN.
    """
    gt = np.asarray(gt_joints_mm, dtype=np.float64)
    depth = np.asarray(depth)
    j = skeleton.num_joints
    if gt.shape != (j, 3):
        raise ValueError(f"ground truth must be ({j}, 3), got {gt.shape}")
    uv = camera.project(gt)
    on_image = camera.on_image(uv)
    noisy = uv.copy()
    if noise_px > 0:
        rng = rng if rng is not None else np.random.default_rng()
        noisy = uv + rng.normal(0.0, noise_px, uv.shape)
    noisy = camera.onto_image(noisy)
    noisy[~on_image] = np.nan
    visible = visible_by_depth(gt, depth, camera, skeleton.surface_offsets_mm)
    parents = skeleton.parent_array
    order = np.zeros(j, dtype=np.int8)
    has_parent = parents >= 0
    dz = gt[:, 2] - gt[np.where(has_parent, parents, 0), 2]
    order[has_parent & (dz > 10.0)] = 1
    order[has_parent & (dz < -10.0)] = -1
    order[~on_image] = 0
    return FrameAnnotation(
        uv_px=noisy,
        visible=visible,
        depth_order=order,
        xyz_mm=np.full((j, 3), np.nan),
        outside=~on_image,
    ).validate(j)


def simulate_annotations(
    sequence, frames, noise_px: float = 0.0, seed: int = 0
) -> dict[int, FrameAnnotation]:
    """Simulated annotations for ``frames`` of a sequence with ground truth (benchmarks only).

    Each frame's 2D noise comes from its own RNG (``seed``, frame), so a frame's annotation does not
    depend on which other frames are requested.
    """
    gt = sequence.ground_truth
    if gt is None:
        raise ValueError(f"{sequence.path}: the simulated annotator needs ground truth")
    out: dict[int, FrameAnnotation] = {}
    for f in frames:
        f = int(f)
        rng = np.random.default_rng([seed, f, 404])
        out[f] = simulate_annotation(
            gt.joints_mm[f], sequence.depth(f), sequence.camera, sequence.skeleton, noise_px, rng
        )
    return out


__all__ = [
    "ARM_MODES",
    "GESTURES",
    "KINECT_SENSOR",
    "MSRA_SENSOR",
    "SENSORS",
    "SR300_SENSOR",
    "SensorModel",
    "pose_arm",
    "write_sequence",
    "PARAM_NAMES",
    "HandModel",
    "Primitives",
    "SynthMotion",
    "add_sensor_noise",
    "forward_kinematics",
    "generate_sequence",
    "gesture_library",
    "hand_primitives",
    "local_pose",
    "build_hand_model",
    "make_hand_model",
    "make_varied_hand_model",
    "render_depth",
    "render_frame",
    "rotation_matrices",
    "simulate_annotation",
    "simulate_annotations",
    "template_hand",
    "synthesize_motion",
]
