"""NYU hand-pose dataset (Tompson et al. 2014): RGB-packed depth PNGs + ``joint_data.mat``.

- Depth: ``depth_<k>_%07d.png`` for camera ``k`` (1 = frontal, the default); the 16-bit depth in mm
  is packed as ``(G << 8) | B`` (OpenCV reads BGR: channel 0 = B, channel 1 = G). 0 = invalid.
  The folder may be the split folder itself (``train/``, ``test/``) or its parent with ``train/``.
- Ground truth: ``joint_data.mat`` -> ``joint_xyz[camera k-1][frame number - 1][36][3]`` in mm with
  y up (z positive forward); converted to the OpenCV frame by ``y -> -y`` and restricted to the 14
  joints of the standard evaluation (:data:`NYU_JOINTS`), skeleton ``nyu14``. Loaded on first access.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import cv2
import numpy as np

from ..camera import NYU_CAMERA, CameraIntrinsics
from ..skeleton import NYU14
from .base import (
    DatasetError,
    DepthSequence,
    FrameError,
    GroundTruth,
    check_frame_header,
    validate_depth,
)

#: the 14 of NYU's 36 joints used by the standard evaluation (and skeleton ``nyu14``).
NYU_JOINTS = (0, 3, 6, 9, 12, 15, 18, 21, 24, 25, 27, 30, 31, 32)
_NAME = re.compile(r"depth_(\d+)_(\d+)\.png$")
JOINT_FILE = "joint_data.mat"


def _numbers(folder: Path, camera_index: int) -> np.ndarray:
    nums = []
    with os.scandir(folder) as it:
        for e in it:
            m = _NAME.match(e.name)
            if m and int(m.group(1)) == camera_index:
                nums.append(int(m.group(2)))
    return np.sort(np.asarray(nums, dtype=np.int64))


def _find_root(path: Path) -> Path | None:
    for candidate in (path, path / "train"):
        if candidate.is_dir():
            with os.scandir(candidate) as it:
                if any(_NAME.match(e.name) for e in it):
                    return candidate
    return None


def looks_like_nyu(path: str | Path) -> bool:
    """Cheap check: ``depth_<k>_%07d.png`` files in the folder or in its ``train/``."""
    path = Path(path)
    return path.is_dir() and _find_root(path) is not None


def decode_nyu_png(image: np.ndarray) -> np.ndarray:
    """``(H, W, 3)`` uint8 BGR -> ``(H, W)`` float32 mm depth ``(G << 8) | B``."""
    g = image[:, :, 1].astype(np.uint16)
    b = image[:, :, 0].astype(np.uint16)
    return ((g << 8) | b).astype(np.float32)


def encode_nyu_png(depth_mm: np.ndarray) -> np.ndarray:
    """Inverse of :func:`decode_nyu_png` (R channel 0): ``(H, W)`` mm -> ``(H, W, 3)`` uint8 BGR."""
    d = np.asarray(np.rint(depth_mm), dtype=np.uint16)
    out = np.zeros(d.shape + (3,), dtype=np.uint8)
    out[:, :, 0] = d & 0xFF
    out[:, :, 1] = d >> 8
    return out


class NYUSequence(DepthSequence):
    """NYU depth frames of one camera (``camera_index``, default 1) with optional ground truth."""

    format = "nyu"

    def __init__(
        self,
        path: str | Path,
        intrinsics: CameraIntrinsics | None = None,
        camera_index: int = 1,
    ):
        path = Path(path)
        if path.is_file() and path.name == JOINT_FILE:
            path = path.parent
        if not path.is_dir():
            raise DatasetError(f"{path}: not a folder (NYU layout needs depth_<k>_%07d.png files)")
        root = _find_root(path)
        if root is None:
            raise DatasetError(f"{path}: no depth_<k>_%07d.png frames found (NYU layout)")
        self._numbers = _numbers(root, camera_index)
        if len(self._numbers) == 0:
            raise DatasetError(
                f"{root}: no depth_{camera_index}_%07d.png frames for camera {camera_index}"
            )
        self.camera_index = camera_index
        super().__init__(root, intrinsics or NYU_CAMERA, NYU14)

    def __len__(self) -> int:
        return len(self._numbers)

    def _name(self, index: int) -> str:
        return f"depth_{self.camera_index}_{int(self._numbers[index]):07d}.png"

    @property
    def frame_names(self) -> list[str]:
        return [self._name(i) for i in range(len(self))]

    def depth(self, index: int) -> np.ndarray:
        index = self._check_index(index)
        path = self.path / self._name(index)
        shape = (self.camera.height, self.camera.width)
        if not path.is_file():
            raise FrameError(path, index, "file missing")
        check_frame_header(path, index, shape)  # before decoding
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise FrameError(path, index, "unreadable PNG")
        if image.ndim != 3 or image.shape[2] < 3 or image.dtype != np.uint8:
            raise FrameError(
                path,
                index,
                f"expected 8-bit 3-channel PNG (RGB-packed depth), got {image.shape} {image.dtype}",
            )
        return validate_depth(decode_nyu_png(image), path, index, shape)

    def _load_ground_truth(self) -> GroundTruth | None:
        """Joints ``(N, 14, 3)`` mm (OpenCV frame) from ``joint_data.mat``, or None if absent."""
        mat = self.path / JOINT_FILE
        if not mat.is_file():
            return None
        import scipy.io

        try:
            xyz = scipy.io.loadmat(str(mat), variable_names=["joint_xyz"]).get("joint_xyz")
        except Exception as exc:  # scipy raises a variety of errors on corrupt files
            raise DatasetError(f"{mat}: cannot read: {exc}") from exc
        if xyz is None:
            raise DatasetError(f"{mat}: no variable 'joint_xyz'")
        xyz = np.asarray(xyz, dtype=np.float64)
        if xyz.ndim != 4 or xyz.shape[2] != 36 or xyz.shape[3] != 3:
            raise DatasetError(
                f"{mat}: joint_xyz has shape {xyz.shape}, expected (cameras, N, 36, 3)"
            )
        if not 1 <= self.camera_index <= xyz.shape[0]:
            raise DatasetError(f"{mat}: no camera {self.camera_index} (has {xyz.shape[0]})")
        per_cam = xyz[self.camera_index - 1]
        rows = self._numbers - 1
        if rows.min() < 0 or rows.max() >= len(per_cam):
            raise DatasetError(
                f"{mat}: has {len(per_cam)} frames but the folder has frame number "
                f"{int(self._numbers.max())} (frame numbers are 1-based rows of joint_xyz)"
            )
        joints = per_cam[rows][:, NYU_JOINTS, :].copy()
        if not np.all(np.isfinite(joints)):
            raise DatasetError(f"{mat}: NaN/inf joint coordinates")
        joints[..., 1] *= -1.0
        return GroundTruth(joints)
