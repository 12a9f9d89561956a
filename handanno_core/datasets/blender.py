"""Oberweger et al.'s synthetic Blender set (CVPR 2016): ``*depth*.npy`` + ``*anno_blender.txt``.

Layout (e.g. ``hpseq_loop_mv/``): ``c00_<id>_depth_0002.npy`` and ``c00_<id>_anno_blender.txt``,
paired by the id (the second ``_``-separated token of the file name) and sorted by it.

- Depth: ``np.load``; ``(H, W)`` or ``(H, W, C)`` float in **metres** (channel 0 used). x1000 -> mm;
  values > 999.9999 m (background, including +inf) or <= 0 become 0 (invalid). NaN is an error.
- Labels: whitespace text, 24 x (u, v, z_m) in image pixels and metres, back-projected to mm in the
  OpenCV frame with the camera. The raw label is kept: the anchor code's 0.85 fingertip shortening
  is an evaluation choice, not a property of the data.
- Camera: fx=460.017965, fy=459.990440, cx=320, cy=240, 640x480 (Blender renderer's camera).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..camera import CameraIntrinsics
from ..skeleton import BLENDER24
from .base import (
    DatasetError,
    FileListSequence,
    FrameError,
    GroundTruth,
    natural_key,
    read_npy,
    validate_depth,
)

BLENDER_CAMERA = CameraIntrinsics(
    fx=460.017965, fy=459.990440, cx=320.0, cy=240.0, width=640, height=480
)
LABEL_SUFFIX = "anno_blender.txt"
#: depth values (metres) above this are background.
MAX_DEPTH_M = 999.9999


def _frame_id(name: str) -> str:
    """The pairing id of a Blender file name: its second ``_`` token (``c00_<id>_...``)."""
    tokens = name.split("_")
    return tokens[1] if len(tokens) > 2 else tokens[0]


def _list(folder: Path) -> tuple[dict[str, str], dict[str, str]]:
    depth, labels = {}, {}
    with os.scandir(folder) as it:
        for e in it:
            name = e.name
            if name.endswith(".npy") and "depth" in name:
                depth[_frame_id(name)] = name
            elif name.endswith(LABEL_SUFFIX):
                labels[_frame_id(name)] = name
    return depth, labels


def looks_like_blender(path: str | Path) -> bool:
    """Cheap check: a folder with ``*anno_blender.txt`` labels or ``c00_<id>_depth*.npy`` frames."""
    path = Path(path)
    if not path.is_dir():
        return False
    with os.scandir(path) as it:
        for e in it:
            if e.name.endswith(LABEL_SUFFIX):
                return True
            if e.name.endswith(".npy") and "_depth" in e.name and e.name.count("_") >= 3:
                return True
    return False


class BlenderSequence(FileListSequence):
    """A folder of Blender ``.npy`` depth frames (metres) with optional ``anno_blender`` labels."""

    format = "blender"

    def __init__(self, path: str | Path, intrinsics: CameraIntrinsics | None = None):
        root = Path(path)
        if not root.is_dir():
            raise DatasetError(f"{root}: not a folder (Blender layout needs *depth*.npy files)")
        depth, labels = _list(root)
        if not depth:
            raise DatasetError(f"{root}: no *depth*.npy frames found (Blender layout)")
        ids = sorted(depth, key=natural_key)
        self._files = [depth[i] for i in ids]
        self._label_files = [labels.get(i) for i in ids]
        super().__init__(root, intrinsics or BLENDER_CAMERA, BLENDER24)

    def depth(self, index: int) -> np.ndarray:
        index, path, shape = self._frame_file(index)
        raw = read_npy(path, index, shape)
        if raw.ndim == 3 and raw.shape[2] >= 1:
            raw = raw[:, :, 0]
        if raw.ndim != 2:
            raise FrameError(path, index, f"expected (H, W) or (H, W, C) depth, got {raw.shape}")
        if raw.dtype.kind not in "fiu":
            raise FrameError(path, index, f"depth has non-numeric dtype {raw.dtype}")
        metres = raw.astype(np.float64, copy=False)
        if np.isnan(metres).any():
            raise FrameError(path, index, f"{int(np.isnan(metres).sum())} NaN depth values")
        invalid = (metres > MAX_DEPTH_M) | (metres <= 0)
        mm = np.where(invalid, 0.0, metres * 1000.0).astype(np.float32)
        return validate_depth(mm, path, index, shape)

    def _load_ground_truth(self) -> GroundTruth | None:
        """Joints ``(N, 24, 3)`` mm (OpenCV frame) from the labels; None if no frame has a label."""
        if all(f is None for f in self._label_files):
            return None
        missing = [d for d, lab in zip(self._files, self._label_files, strict=True) if lab is None]
        if missing:
            raise DatasetError(
                f"{self.path}: {len(missing)} depth frame(s) have no *{LABEL_SUFFIX}, e.g. {missing[0]}"
            )
        uvz = np.empty((len(self), 24, 3))
        for i, name in enumerate(self._label_files):
            uvz[i] = read_blender_label(self.path / name, i)
        uvz[..., 2] *= 1000.0
        return GroundTruth(self.camera.backproject(uvz[..., :2], uvz[..., 2]))


def read_blender_label(path: str | Path, frame: int) -> np.ndarray:
    """Parse one ``anno_blender.txt``: ``(24, 3)`` = (u px, v px, z metres); DatasetError if bad."""
    try:
        text = Path(path).read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path} (frame {frame}): cannot read label: {exc}") from exc
    try:
        values = np.array(text.split(), dtype=np.float64)
    except ValueError:
        raise DatasetError(f"{path} (frame {frame}): non-numeric value in label") from None
    if values.size != 72:
        raise DatasetError(
            f"{path} (frame {frame}): {values.size} values, expected 72 (24 joints x (u, v, z))"
        )
    if not np.all(np.isfinite(values)):
        raise DatasetError(f"{path} (frame {frame}): NaN/inf in label")
    return values.reshape(24, 3)
