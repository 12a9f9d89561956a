"""A generic folder of depth frames: 16-bit PNG or ``.npy`` (mm), plus intrinsics.

- Frames: ``*.png`` (single-channel uint16; depth_mm = value x ``depth_scale_mm``) or, if there is no
  PNG, ``*.npy`` (``(H, W)`` float mm). Sorted naturally by the numbers in the file names
  (``2.png`` before ``10.png``). ``joints.npy`` is not a frame.
- Camera: the ``intrinsics=`` argument, else ``intrinsics.json`` in the folder
  (``fx, fy, cx, cy, width, height`` and optionally ``depth_scale_mm``). Neither: :class:`DatasetError`.
- ``depth_scale_mm``: the argument, else the JSON key, else 1.0.
- Sequence breaks (frames where an unrelated recording starts; smoothing, selection and
  refinement never cross them): ``breaks.txt`` in the folder if present (one frame index or
  frame file name per line, ``#`` comments), else read off the file names: a change of the text
  around the last number (``take1_0007.png`` -> ``take2_0000.png``), a number that does not
  increase, or a jump of more than 5x the usual step (frame numbers or timestamps with a pause).
  ``handanno new --breaks`` overrides both, for any format.
- Ground truth only if ``joints.npy`` ``(N, J, 3)`` mm (OpenCV frame) is present; the skeleton is
  chosen by J (21 -> msra21, 24 -> blender24, 16 -> icvl16, 14 -> nyu14); default msra21.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..camera import CameraIntrinsics
from ..fileio import read_json_object
from ..skeleton import MSRA21, SKELETONS
from .base import (
    DatasetError,
    FileListSequence,
    FrameError,
    GroundTruth,
    breaks_from_names,
    natural_key,
    read_breaks_file,
    read_npy,
    read_png16,
    validate_depth,
)

INTRINSICS_FILE = "intrinsics.json"
JOINTS_FILE = "joints.npy"
BREAKS_FILE = "breaks.txt"
_SKELETON_BY_J = {s.num_joints: s for s in SKELETONS.values()}


def _frames(folder: Path) -> tuple[list[str], str]:
    pngs, npys = [], []
    with os.scandir(folder) as it:
        for e in it:
            name = e.name
            low = name.lower()
            if low.endswith(".png"):
                pngs.append(name)
            elif low.endswith(".npy") and name != JOINTS_FILE:
                npys.append(name)
    if pngs:
        return sorted(pngs, key=natural_key), "png"
    return sorted(npys, key=natural_key), "npy"


def looks_like_folder(path: str | Path) -> bool:
    """Cheap check: a folder with ``.png`` or ``.npy`` frames."""
    path = Path(path)
    return path.is_dir() and bool(_frames(path)[0])


class FolderSequence(FileListSequence):
    """Depth frames in a plain folder; see the module docstring."""

    format = "folder"

    def __init__(
        self,
        path: str | Path,
        intrinsics: CameraIntrinsics | None = None,
        depth_scale_mm: float | None = None,
    ):
        root = Path(path)
        if not root.is_dir():
            raise DatasetError(f"{root}: not a folder of depth frames")
        names, kind = _frames(root)
        if not names:
            raise DatasetError(f"{root}: no .png or .npy depth frames found")
        meta: dict = {}
        meta_path = root / INTRINSICS_FILE
        if meta_path.is_file():
            try:
                meta = read_json_object(meta_path, "camera intrinsics")
            except ValueError as exc:
                raise DatasetError(str(exc)) from exc
        if intrinsics is None:
            if not meta:
                raise DatasetError(
                    f"{root}: no camera intrinsics: put {INTRINSICS_FILE} "
                    "(fx, fy, cx, cy, width, height[, depth_scale_mm]) in the folder or pass intrinsics"
                )
            try:
                intrinsics = CameraIntrinsics.from_json(meta_path)
            except ValueError as exc:
                raise DatasetError(str(exc)) from exc
        if depth_scale_mm is None:
            depth_scale_mm = meta.get("depth_scale_mm", 1.0)
        try:
            scale = float(depth_scale_mm)
        except (TypeError, ValueError):
            scale = float("nan")
        if not (np.isfinite(scale) and scale > 0):
            raise DatasetError(
                f"{root}: depth_scale_mm must be a number > 0, got {depth_scale_mm!r}"
            )
        self.depth_scale_mm = scale
        self._files = names
        self._kind = kind
        skeleton = MSRA21
        self._joints_path = root / JOINTS_FILE
        if self._joints_path.is_file():
            skeleton = self._joints_skeleton(len(names))
        super().__init__(root, intrinsics, skeleton)
        breaks_path = root / BREAKS_FILE
        if breaks_path.is_file():
            self._breaks = read_breaks_file(breaks_path, names, len(names))
        else:
            self._breaks = breaks_from_names(names)

    def _joints_skeleton(self, n: int):
        """Read only the header of joints.npy (memory-mapped) to pick the skeleton and check N."""
        try:
            arr = np.load(self._joints_path, mmap_mode="r", allow_pickle=False)
        except (OSError, ValueError, EOFError) as exc:
            raise DatasetError(f"{self._joints_path}: cannot read: {exc}") from exc
        if arr.ndim != 3 or arr.shape[2] != 3:
            raise DatasetError(f"{self._joints_path}: shape {arr.shape}, expected (N, J, 3)")
        if arr.shape[0] != n:
            raise DatasetError(
                f"{self._joints_path}: {arr.shape[0]} poses but the folder has {n} frames"
            )
        if arr.shape[1] not in _SKELETON_BY_J:
            raise DatasetError(
                f"{self._joints_path}: {arr.shape[1]} joints matches no known skeleton "
                f"({', '.join(f'{s.name}: {j}' for j, s in _SKELETON_BY_J.items())})"
            )
        return _SKELETON_BY_J[arr.shape[1]]

    @property
    def sequence_breaks(self) -> list[int]:
        """From ``breaks.txt`` or the file names (module docstring)."""
        return list(self._breaks)

    def depth(self, index: int) -> np.ndarray:
        index, path, shape = self._frame_file(index)
        if self._kind == "png":
            return read_png16(path, index, shape, self.depth_scale_mm)
        raw = read_npy(path, index, shape)
        if raw.dtype.kind not in "fiu":
            raise FrameError(path, index, f"depth has non-numeric dtype {raw.dtype}")
        if raw.shape != shape:
            raise FrameError(path, index, f"depth has shape {raw.shape}, expected {shape}")
        return validate_depth(raw.astype(np.float32), path, index, shape)

    def _load_ground_truth(self) -> GroundTruth | None:
        """``joints.npy`` ``(N, J, 3)`` mm if present, else None."""
        if not self._joints_path.is_file():
            return None
        joints = np.load(self._joints_path, allow_pickle=False).astype(np.float64)
        if not np.all(np.isfinite(joints)):
            raise DatasetError(f"{self._joints_path}: NaN/inf joint coordinates")
        return GroundTruth(joints)
