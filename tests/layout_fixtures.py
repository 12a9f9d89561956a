"""Small NYU-layout and ICVL-layout sequences written from the synthetic renderer.

The synthetic hand (MSRA-21 joints, :func:`handanno_core.synth.synthesize_motion`) is rendered with
each dataset's camera and written in that dataset's file format, with its ground truth mapped onto
the dataset's joints:

* NYU (``nyu14``, 640x480 Kinect intrinsics): ``depth_1_%07d.png`` (RGB-packed depth) and
  ``joint_data.mat`` (``joint_xyz`` (1, N, 36, 3), y up; the 14 evaluated joints filled). The hand
  is moved 380 mm further away (NYU hands are 600-900 mm from the camera). Fingers: tip and PIP
  ("mid"); thumb: tip, IP ("mid"), MCP ("root"); ``wrist1``/``wrist2`` 14 mm to the little/thumb
  side of the wrist; ``palm`` halfway between the wrist and the middle MCP.
* ICVL (``icvl16``, 320x240): ``Depth/seq/image_%04d.png`` (uint16 mm) and ``labels.txt``
  (file, then 16 x (u, v, d)). ``palm`` a third of the way from the wrist to the middle MCP; per
  finger root = MCP, mid = PIP, tip; thumb root = CMC, mid = MCP, tip (the mapping whose
  angles fall inside the ranges learned on the real ICVL labels: 5 deg mean excess at the thumb
  root against 20 deg with root = MCP).

``motion="fpha"``: the hand follows a real recorded trajectory instead (the first FPHA
``Subject_1`` sequence in ``../shared/data/real-motion``, the tune side; the hand model fitted to
its joints, :func:`handanno_core.real_motion.model_of_joints`), rendered and written the same way.

Used by tests/test_layouts.py (into tmp_path) and benchmarks/bench_lift.py ``--layouts``.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from handanno_core import real_motion as rm
from handanno_core.camera import NYU_CAMERA
from handanno_core.datasets.icvl import ICVL_CAMERA
from handanno_core.datasets.nyu import NYU_JOINTS, encode_nyu_png
from handanno_core.synth import render_frame, synthesize_motion

NYU_SHIFT_MM = np.array([0.0, 0.0, 380.0])


def nyu_joints(msra: np.ndarray) -> np.ndarray:
    """``(N, 21, 3)`` MSRA-21 joints -> ``(N, 14, 3)`` nyu14 joints (see module docstring)."""
    lateral = msra[:, 1] - msra[:, 13]
    lateral /= np.linalg.norm(lateral, axis=-1, keepdims=True)
    wrist = msra[:, 0]
    out = np.stack(
        [
            msra[:, 16],
            msra[:, 14],
            msra[:, 12],
            msra[:, 10],
            msra[:, 8],
            msra[:, 6],
            msra[:, 4],
            msra[:, 2],
            msra[:, 20],
            msra[:, 19],
            msra[:, 18],
            wrist - 14.0 * lateral,
            wrist + 14.0 * lateral,
            0.5 * (wrist + msra[:, 5]),
        ],
        axis=1,
    )
    return out


def icvl_joints(msra: np.ndarray) -> np.ndarray:
    """``(N, 21, 3)`` MSRA-21 joints -> ``(N, 16, 3)`` icvl16 joints (see module docstring)."""
    palm = msra[:, 0] + (msra[:, 5] - msra[:, 0]) / 3.0
    idx = [17, 18, 20, 1, 2, 4, 5, 6, 8, 9, 10, 12, 13, 14, 16]
    return np.concatenate([palm[:, None], msra[:, idx]], axis=1)


def has_real_motion() -> bool:
    """Whether the FPHA trajectories of ``motion="fpha"`` are available."""
    return bool(rm.fpha_sequences(rm.DEFAULT_REAL_MOTION, "Subject_1"))


def _motion(frames: int, seed: int, motion: str):
    """Hand model, MSRA-21 joints ``(frames, 21, 3)`` mm and rotations ``(frames, 3, 3)`` of a
    synthetic (``"synthetic"``) or real recorded (``"fpha"``) motion."""
    if motion == "synthetic":
        m = synthesize_motion(frames, seed)
        return m.model, m.joints_mm, m.rotation
    if motion == "fpha":
        first = rm.fpha_sequences(rm.DEFAULT_REAL_MOTION, "Subject_1")[0]
        joints = rm.load_fpha(first)[:frames]
        if len(joints) < frames:
            raise ValueError(f"{first}: {len(joints)} frames, {frames} asked")
        return rm.model_of_joints(joints), joints, rm.rotation_of_joints(joints)
    raise ValueError(f"unknown motion {motion!r}")


def write_nyu_fixture(
    out: str | Path, frames: int = 40, seed: int = 3, motion: str = "synthetic"
) -> Path:
    """Render ``frames`` frames of ``motion`` into an NYU-format folder ``out``; returns it."""
    import scipy.io

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    model, joints, rotation = _motion(frames, seed, motion)
    joints = joints + NYU_SHIFT_MM
    for f in range(frames):
        depth = render_frame(model, joints[f], rotation[f], NYU_CAMERA, noise_seed=(seed, f))
        cv2.imwrite(str(out / f"depth_1_{f + 1:07d}.png"), encode_nyu_png(depth))
    xyz = np.zeros((1, frames, 36, 3))
    nyu = nyu_joints(joints)
    nyu[..., 1] *= -1.0  # NYU's joint_xyz has y up
    xyz[0][:, list(NYU_JOINTS)] = nyu
    scipy.io.savemat(str(out / "joint_data.mat"), {"joint_xyz": xyz})
    return out


def write_icvl_fixture(
    out: str | Path, frames: int = 40, seed: int = 3, motion: str = "synthetic"
) -> Path:
    """Render ``frames`` frames of ``motion`` into an ICVL-format folder ``out``; returns it."""
    out = Path(out)
    (out / "Depth" / "seq").mkdir(parents=True, exist_ok=True)
    model, msra, rotation = _motion(frames, seed, motion)
    joints = icvl_joints(msra)
    uv = ICVL_CAMERA.project(joints)
    lines = []
    for f in range(frames):
        depth = render_frame(model, msra[f], rotation[f], ICVL_CAMERA, noise_seed=(seed, f))
        name = f"seq/image_{f:04d}.png"
        cv2.imwrite(str(out / "Depth" / name), np.rint(depth).astype(np.uint16))
        uvd = np.concatenate([uv[f], joints[f, :, 2:]], axis=1)
        lines.append(name + " " + " ".join(f"{v:.3f}" for v in uvd.ravel()))
    (out / "labels.txt").write_text("\n".join(lines) + "\n")
    return out
