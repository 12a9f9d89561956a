"""Real recorded hand motion (``shared/data/real-motion``) as 21-joint trajectories for the renderer.

Readers for the three joint-trajectory sets of ``real-motion/README.md`` (no depth images there):
FPHA (21 joints, mm, camera frame), NYU (14 joints, u v d) and ICVL (16 joints, u v d), and the
inverse kinematics that fits the MSRA21 hand of :mod:`handanno_core.synth` to a layout with fewer
joints: :func:`fit_skeleton` finds one hand per sequence (bone lengths, palm breadth, where the
layout's joints sit on it) and per frame its joint angles, rotation and position, so that the hand's
*markers* (the points that correspond to the layout's joints) reproduce the recorded joints. The
fitted 21-joint motion is rendered by the synthetic renderer and is that sequence's ground truth.

A marker is either a point on a bone, ``J[a] + t (J[b] - J[a])`` with ``t`` fitted per sequence
(NYU's "mid" finger joint lies between PIP and DIP), or a point fixed in the hand frame,
``wrist + R offset`` with ``offset`` fitted per sequence (palm centre, the two wrist points).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix

from . import lm
from .camera import CameraIntrinsics
from .skeleton import FPHA_TO_MSRA21 as _FPHA_TO_MSRA21
from .skeleton import MSRA21, hand_rotation
from .synth import (
    GESTURES,
    PARAM_HI,
    PARAM_LO,
    HandModel,
    build_hand_model,
    forward_kinematics,
)


def _find_real_motion() -> Path:
    """``shared/data/real-motion`` in the repository's parent folder or the nearest ancestor that has
    one (git worktrees live one level deeper); ``$HANDANNO_REAL_MOTION`` overrides."""
    env = os.environ.get("HANDANNO_REAL_MOTION")
    if env:
        return Path(env)
    here = Path(__file__).resolve()
    for folder in here.parents[1:]:
        candidate = folder / "shared" / "data" / "real-motion"
        if candidate.is_dir():
            return candidate
    return here.parents[2] / "shared" / "data" / "real-motion"


#: the real-motion data (see :func:`_find_real_motion`)
DEFAULT_REAL_MOTION = _find_real_motion()

#: FPHA joint index of each MSRA21 joint (:data:`handanno_core.skeleton.FPHA_TO_MSRA21`)
FPHA_TO_MSRA21 = np.asarray(_FPHA_TO_MSRA21)
#: FPHA depth camera (Intel RealSense SR300), 640x480
FPHA_CAMERA = CameraIntrinsics(
    fx=475.065948, fy=475.065948, cx=315.944855, cy=245.287079, width=640, height=480
)
#: cameras the NYU and ICVL labels' (u, v, d) are given for (real-motion README)
NYU_LABEL_CAMERA = CameraIntrinsics(
    fx=588.036865, fy=587.075073, cx=320.0, cy=240.0, width=640, height=480
)
ICVL_LABEL_CAMERA = CameraIntrinsics(
    fx=240.99, fy=240.96, cx=160.0, cy=120.0, width=320, height=240
)


# ---------------------------------------------------------------------------- readers
def load_fpha(skeleton_txt: str | Path) -> np.ndarray:
    """One FPHA sequence ``(N, 21, 3)`` mm, camera frame, in MSRA21 joint order."""
    path = Path(skeleton_txt)
    data = np.loadtxt(path, ndmin=2)
    if data.size == 0 or data.shape[1] != 64:
        raise ValueError(f"{path}: expected lines of a frame index and 21 x 3 joints (64 columns)")
    return data[:, 1:].reshape(-1, 21, 3)[:, FPHA_TO_MSRA21]


def fpha_sequences(root: str | Path, subject: str) -> list[Path]:
    """The ``skeleton.txt`` files of one FPHA subject (``Subject_1``), sorted."""
    return sorted((Path(root) / "fpha" / subject).glob("*/*/skeleton.txt"))


def _uvd_to_xyz(uvd: np.ndarray, camera: CameraIntrinsics) -> np.ndarray:
    return camera.backproject(uvd[..., :2], uvd[..., 2])


def load_nyu(root: str | Path) -> np.ndarray:
    """The NYU test labels ``(8252, 14, 3)`` mm, camera frame (NYU14 order)."""
    path = Path(root) / "nyu" / "nyu_test_groundtruth_label.txt"
    uvd = np.loadtxt(path)
    if uvd.ndim != 2 or uvd.shape[1] != 42:
        raise ValueError(f"{path}: expected 42 columns (14 joints x u, v, d)")
    return _uvd_to_xyz(uvd.reshape(-1, 14, 3), NYU_LABEL_CAMERA)


def load_icvl(root: str | Path, sequence: int = 1) -> np.ndarray:
    """ICVL test sequence ``sequence`` (1 or 2) ``(N, 16, 3)`` mm, camera frame (ICVL16 order)."""
    path = Path(root) / "icvl" / f"test_seq_{sequence}.txt"
    rows = [line.split()[1:] for line in path.read_text().splitlines() if line.strip()]
    uvd = np.asarray(rows, dtype=np.float64)
    if uvd.ndim != 2 or uvd.shape[1] != 48:
        raise ValueError(f"{path}: expected a file name then 48 numbers (16 joints x u, v, d)")
    return _uvd_to_xyz(uvd.reshape(-1, 16, 3), ICVL_LABEL_CAMERA)


# ---------------------------------------------------------------------------- markers
@dataclass(frozen=True)
class Marker:
    """Where a layout's joint sits on the MSRA21 hand: on bone ``a``-``b`` at fraction ``t``
    (``kind="bone"``), or at ``offset`` mm from the wrist in the hand frame (``kind="local"``);
    ``t``/``offset`` are starting values, fitted per sequence."""

    kind: str
    a: int = 0
    b: int = 0
    t: float = 0.0
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)


def _bone(a: int, b: int, t: float) -> Marker:
    return Marker("bone", a, b, t)


#: NYU14: (tip, mid) of little, ring, middle, index; thumb tip, mid, root; wrist1, wrist2, palm
NYU14_MARKERS = (
    _bone(15, 16, 1.0),
    _bone(14, 15, 0.0),
    _bone(11, 12, 1.0),
    _bone(10, 11, 0.0),
    _bone(7, 8, 1.0),
    _bone(6, 7, 0.0),
    _bone(3, 4, 1.0),
    _bone(2, 3, 0.0),
    _bone(19, 20, 1.0),
    _bone(19, 20, 0.0),
    _bone(18, 19, 0.0),
    Marker("local", offset=(14.0, 0.0, 0.0)),
    Marker("local", offset=(-14.0, 0.0, 0.0)),
    Marker("local", offset=(0.0, 45.0, 0.0)),
)
#: ICVL16: palm, then (root, mid, tip) of thumb, index, middle, ring, little
ICVL16_MARKERS = (Marker("local", offset=(0.0, 25.0, 0.0)),) + tuple(
    m
    for root, pip, dip, tip in (
        (17, 18, 19, 20),
        (1, 2, 3, 4),
        (5, 6, 7, 8),
        (9, 10, 11, 12),
        (13, 14, 15, 16),
    )
    for m in (_bone(root, pip, 0.0), _bone(pip, dip, 0.0), _bone(dip, tip, 1.0))
)


# ---------------------------------------------------------------------------- hand frame
def rotation_of_joints(joints_mm: np.ndarray) -> np.ndarray:
    """Hand-frame rotations ``(N, 3, 3)`` of MSRA21 poses ``(N, 21, 3)``."""
    j = np.asarray(joints_mm, dtype=np.float64)
    mcps = j[:, [1, 5, 9, 13]].mean(axis=1)
    return hand_rotation(j[:, 0], j[:, 1], j[:, 13], mcps)


def model_of_joints(joints_mm: np.ndarray) -> HandModel:
    """A synthetic hand for recorded MSRA21 poses ``(N, 21, 3)``: their median bone lengths, palm
    breadth and (by the middle finger's length) scaled finger radii and palm thickness."""
    j = np.asarray(joints_mm, dtype=np.float64)
    lengths = MSRA21.estimate_bone_lengths(j)
    template = np.asarray(MSRA21.template_bone_lengths_mm)
    size = float(lengths[4:8].sum() / template[4:8].sum())
    breadth = float(np.median(np.linalg.norm(j[:, 1] - j[:, 13], axis=-1)) / 52.0)
    base = build_hand_model(lengths, breadth)
    return build_hand_model(lengths, breadth, base.finger_radii * size, thickness_scale=size)


# ---------------------------------------------------------------------------- inverse kinematics
@dataclass
class SkeletonFit:
    """A 21-joint hand fitted to recorded joints of another layout (see :func:`fit_skeleton`)."""

    model: HandModel
    params_deg: np.ndarray  # (N, 21)
    rotation: np.ndarray  # (N, 3, 3) local-to-camera
    centre_mm: np.ndarray  # (N, 3) palm centre
    joints_mm: np.ndarray  # (N, 21, 3) camera frame
    markers_mm: np.ndarray  # (N, K, 3) the fitted hand's points for the layout's joints
    residual_mm: np.ndarray  # (N, K) distance marker - recorded joint

    def summary(self) -> dict:
        r = self.residual_mm
        return {
            "mean_mm": round(float(r.mean()), 3),
            "median_mm": round(float(np.median(r)), 3),
            "p95_mm": round(float(np.percentile(r, 95)), 3),
            "max_mm": round(float(r.max()), 3),
            "per_joint_mean_mm": [round(float(x), 2) for x in r.mean(axis=0)],
        }


def _rodrigues(w: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(N, 3, 3)`` of rotation vectors ``(N, 3)`` (radians)."""
    theta = np.linalg.norm(w, axis=-1)
    k = w / np.maximum(theta, 1e-12)[:, None]
    kx = np.zeros(w.shape[:-1] + (3, 3))
    kx[:, 0, 1], kx[:, 0, 2], kx[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    kx = kx - kx.transpose(0, 2, 1)
    s, c = np.sin(theta)[:, None, None], np.cos(theta)[:, None, None]
    return np.eye(3) + s * kx + (1 - c) * kx @ kx


#: bone-length factors: prior SD of their logarithm (per bone, around the global scale); the
#: residual weight turns one SD into this many mm of marker error
_BONE_LOG_SD = 0.08
_PRIOR_MM = 2.0
#: prior SD of a bone marker's position along its bone (fraction of the bone) around its start
#: value: without it the global scale trades off against where the markers sit
_MARKER_T_SD = 0.25
#: prior SD (mm) of a hand-frame marker (palm centre, wrist sides) around its start value: without
#: it the metacarpals' lengths trade off against where the palm markers sit
_MARKER_OFFSET_SD_MM = 10.0
#: soft couplings per frame (mm per degree): DIP = 2/3 PIP, thumb MCP abduction 0
_COUPLING_MM_PER_DEG = 0.05


def _start(y: np.ndarray, markers, bone_idx: list, local_idx: list, template: np.ndarray):
    """The fit's start: per-frame rotations ``(N, 3, 3)`` from the recorded palm, the hand scale
    and the palm centres ``(N, 3)`` mm from the recorded wrist-side joints ``y`` (N, K, 3)."""

    def landmark(*joints: int) -> np.ndarray:
        for joint in joints:
            hits = [i for i in bone_idx if markers[i].a == joint]
            if hits:
                return y[:, hits].mean(axis=1)
        raise ValueError("markers name no index or little finger joint")

    index_pt, little_pt = landmark(1, 2), landmark(13, 14)
    finger_pts = y[:, [i for i in bone_idx if markers[i].a in (1, 2, 5, 6, 9, 10, 13, 14)]].mean(1)
    wrist_pt = y[:, local_idx].mean(axis=1)
    rot0 = hand_rotation(wrist_pt, index_pt, little_pt, finger_pts)
    scale0 = float(np.median(np.linalg.norm(finger_pts - wrist_pt, axis=-1)) / 75.0)
    scale0 = float(np.clip(scale0, 0.6, 1.5))
    model0 = build_hand_model(template * scale0, scale0)
    centre0 = wrist_pt + np.einsum("nij,j->ni", rot0, model0.palm_centre - model0.local_base[0])
    return rot0, scale0, centre0


def _stage1_sparsity(m: int, per_frame: int, rows_per_frame: int, n_prior: int, n_shared: int):
    """Jacobian sparsity of the first stage: each frame's rows see its own pose and the shared
    unknowns; the prior rows their own shared unknown (bone factors, then marker t/offsets)."""
    s0 = m * per_frame
    sparsity = lil_matrix((m * rows_per_frame + n_prior, s0 + n_shared), dtype=np.int8)
    for f in range(m):
        sparsity[
            f * rows_per_frame : (f + 1) * rows_per_frame, f * per_frame : (f + 1) * per_frame
        ] = 1
    sparsity[: m * rows_per_frame, s0:] = 1
    sparsity[m * rows_per_frame : m * rows_per_frame + 21, s0 + 1 : s0 + 22] = 1
    for k in range(n_prior - 21):
        sparsity[m * rows_per_frame + 21 + k, s0 + 22 + k] = 1
    return sparsity


def fit_skeleton(
    targets_mm: np.ndarray,
    markers: tuple[Marker, ...],
    *,
    shape_frames: int = 30,
    shape_iterations: int = 30,
    pose_iterations: int = 30,
) -> SkeletonFit:
    """Inverse kinematics of the synthetic MSRA21 hand to recorded joints ``(N, K, 3)`` mm.

    Unknowns: per sequence, the global scale, a factor per bone (log-normal prior, SD
    ``_BONE_LOG_SD``), the palm breadth, each marker's ``t`` or ``offset``; per frame, the 21
    articulation parameters of :func:`handanno_core.synth.local_pose` (bounded 15 deg beyond the
    generator's ranges), a rotation (axis-angle around a start from the recorded palm) and the palm
    centre. Least squares on the marker errors (mm) plus soft priors, in two stages: the sequence's
    hand together with the poses of ``shape_frames`` frames spread over the sequence (trust-region
    reflective, sparse Jacobian), then every frame's pose with that hand fixed (a batched
    Levenberg-Marquardt: frames are independent, 27 unknowns each). ``markers`` maps the ``K``
    recorded joints onto the hand.
    """
    y = np.asarray(targets_mm, dtype=np.float64)
    n, k_count = y.shape[:2]
    if len(markers) != k_count:
        raise ValueError(f"{k_count} recorded joints but {len(markers)} markers")
    template = np.asarray(MSRA21.template_bone_lengths_mm, dtype=np.float64)
    bone_idx = [i for i, m in enumerate(markers) if m.kind == "bone"]
    local_idx = [i for i, m in enumerate(markers) if m.kind == "local"]

    rot0, scale0, centre0 = _start(y, markers, bone_idx, local_idx, template)

    relaxed = np.clip(np.asarray(GESTURES["relaxed"], dtype=np.float64), PARAM_LO, PARAM_HI)
    per_frame = 21 + 3 + 3
    frames0 = np.hstack([np.tile(relaxed, (n, 1)), np.zeros((n, 3)), centre0])
    shared0 = np.concatenate(
        [
            [np.log(scale0)],
            np.zeros(20),
            [0.0],
            [markers[i].t for i in bone_idx],
            np.concatenate([markers[i].offset for i in local_idx]) * scale0,
        ]
    )
    frame_lo = np.concatenate([PARAM_LO - 15.0, [-np.pi] * 3, [-np.inf] * 3])
    frame_hi = np.concatenate([PARAM_HI + 15.0, [np.pi] * 3, [np.inf] * 3])
    shared_lo = np.full(shared0.size, -np.inf)
    shared_hi = np.full(shared0.size, np.inf)
    shared_lo[22 : 22 + len(bone_idx)] = -0.5
    shared_hi[22 : 22 + len(bone_idx)] = 1.5
    frames0 = np.clip(frames0, frame_lo + 1e-9, frame_hi - 1e-9)
    dip_pairs = [(4 * f + 2, 4 * f + 3) for f in range(4)]

    def hand(shared: np.ndarray) -> HandModel:
        scale = np.exp(shared[0])
        return build_hand_model(template * scale * np.exp(shared[1:21]), scale * np.exp(shared[21]))

    def predict(model: HandModel, shared: np.ndarray, frames: np.ndarray, sel: np.ndarray):
        """Markers ``(M, K, 3)``, joints and rotations of frames ``(M, 27)`` (rows ``sel`` of y)."""
        rotation = rot0[sel] @ _rodrigues(frames[:, 21:24])
        joints = forward_kinematics(model, frames[:, :21], rotation, frames[:, 24:])
        ts = shared[22 : 22 + len(bone_idx)]
        offsets = shared[22 + len(bone_idx) :].reshape(-1, 3)
        out = np.empty((len(frames), k_count, 3))
        for t, i in zip(ts, bone_idx, strict=True):
            m = markers[i]
            out[:, i] = joints[:, m.a] + t * (joints[:, m.b] - joints[:, m.a])
        for off, i in zip(offsets, local_idx, strict=True):
            out[:, i] = joints[:, 0] + rotation @ off
        return out, joints, rotation

    def frame_residuals(model, shared, frames, sel) -> np.ndarray:
        """``(M, R)``: marker errors (mm) and the couplings of each frame."""
        pred, _, _ = predict(model, shared, frames, sel)
        params = frames[:, :21]
        coupling = [params[:, dip] - 2.0 / 3.0 * params[:, pip] for pip, dip in dip_pairs]
        coupling.append(params[:, 19])
        return np.concatenate(
            [
                (pred - y[sel]).reshape(len(frames), -1),
                _COUPLING_MM_PER_DEG * np.stack(coupling, 1),
            ],
            axis=1,
        )

    # --- stage 1: the hand and the poses of a few frames, jointly
    sel = np.unique(np.linspace(0, n - 1, min(shape_frames, n)).round().astype(np.int64))
    m = len(sel)
    s0 = m * per_frame

    def residuals(x: np.ndarray) -> np.ndarray:
        shared = x[s0:]
        r = frame_residuals(hand(shared), shared, x[:s0].reshape(m, per_frame), sel)
        prior = np.concatenate(
            [
                _PRIOR_MM / _BONE_LOG_SD * shared[1:21],
                [_PRIOR_MM / 0.1 * shared[21]],
                _PRIOR_MM / _MARKER_T_SD * (shared[22 : 22 + len(bone_idx)] - t0),
                _PRIOR_MM / _MARKER_OFFSET_SD_MM * (shared[22 + len(bone_idx) :] - offset0),
            ]
        )
        return np.concatenate([r.ravel(), prior])

    rows_per_frame = k_count * 3 + len(dip_pairs) + 1
    t0 = np.array([markers[i].t for i in bone_idx])
    offset0 = shared0[22 + len(bone_idx) :].copy()
    n_prior = 21 + len(bone_idx) + offset0.size
    sparsity = _stage1_sparsity(m, per_frame, rows_per_frame, n_prior, shared0.size)
    sol = least_squares(
        residuals,
        np.concatenate([frames0[sel].ravel(), shared0]),
        jac_sparsity=sparsity.tocsr(),
        bounds=(
            np.concatenate([np.tile(frame_lo, m), shared_lo]),
            np.concatenate([np.tile(frame_hi, m), shared_hi]),
        ),
        method="trf",
        tr_solver="lsmr",
        x_scale="jac",
        max_nfev=shape_iterations,
    )
    shared = sol.x[s0:]
    model = hand(shared)
    frames0[sel] = sol.x[:s0].reshape(m, per_frame)

    # --- stage 2: every frame's pose, the hand fixed (batched Levenberg-Marquardt)
    everyone = np.arange(n)
    frames = _batched_lm(
        lambda x: frame_residuals(model, shared, x, everyone),
        frames0,
        frame_lo,
        frame_hi,
        iterations=pose_iterations,
    )
    pred, joints, rotation = predict(model, shared, frames, everyone)
    return SkeletonFit(
        model=model,
        params_deg=frames[:, :21],
        rotation=rotation,
        centre_mm=frames[:, 24:],
        joints_mm=joints,
        markers_mm=pred,
        residual_mm=np.linalg.norm(pred - y, axis=-1),
    )


def _batched_lm(
    fun, x0: np.ndarray, lo: np.ndarray, hi: np.ndarray, *, iterations: int
) -> np.ndarray:
    """Levenberg-Marquardt on ``M`` independent small problems at once.

    ``fun`` maps ``(M, P)`` unknowns to ``(M, R)`` residuals, row ``i`` depending only on row ``i``;
    forward-difference Jacobians (one ``fun`` call per unknown), damped normal equations solved per
    row, steps clipped into ``[lo, hi]`` and kept only where they lower that row's cost.
    """
    p = x0.shape[1]
    eps = np.where(np.isfinite(hi - lo) & (hi - lo < 10.0), 1e-6, 1e-4)  # radians vs deg / mm

    def evaluate(x: np.ndarray) -> _Residuals:
        r = fun(x)
        return _Residuals(np.sum(r * r, axis=1), r)

    def normal_equations(x: np.ndarray, ev: _Residuals) -> lm.BatchedNormalEquations:
        jac = np.empty(ev.r.shape + (p,))
        for k in range(p):
            xk = x.copy()
            xk[:, k] += eps[k]
            jac[:, :, k] = (fun(xk) - ev.r) / eps[k]
        jtj = np.einsum("mrp,mrq->mpq", jac, jac)
        jtr = np.einsum("mrp,mr->mp", jac, ev.r)
        return lm.BatchedNormalEquations(jtj, jtr, np.einsum("mpp->mp", jtj), shift=1e-9)

    fit = lm.levenberg_marquardt_batched(
        evaluate,
        x0.copy(),
        normal_equations=normal_equations,
        retract=lambda x, step: np.clip(x + step, lo, hi),
        max_iter=iterations,
        lam0=1e-3,
        up=10.0,
        down=0.3,
    )
    return fit.x


@dataclass
class _Residuals:
    """Per-row cost ``(M,)`` and residuals ``r`` ``(M, R)``."""

    cost: np.ndarray
    r: np.ndarray
