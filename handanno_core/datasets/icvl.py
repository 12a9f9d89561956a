"""ICVL hand-posture dataset (Tang et al. 2014): 16-bit PNG depth + a label text file.

Label file (``labels.txt``, ``test_seq_1.txt`` ...): one line per frame,
``relative/file.png u1 v1 d1 ... u16 v16 d16`` (pixels and depth in mm). The PNG is looked up as
``<root>/Depth/<relative>`` (or ``<root>/<relative>``), ``root`` = the label file's folder.
Depth is uint16 mm (times ``depth_scale_mm``, default 1). Ground truth = the labels back-projected
with the camera (fx = fy = 241.42, c = (160, 120), 320x240), skeleton ``icvl16``.

Open the dataset folder (the first label file in natural order is used) or a label file directly.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..camera import CameraIntrinsics
from ..skeleton import ICVL16
from .base import (
    DatasetError,
    FileListSequence,
    GroundTruth,
    natural_key,
    read_png16,
)

ICVL_CAMERA = CameraIntrinsics(fx=241.42, fy=241.42, cx=160.0, cy=120.0, width=320, height=240)
_VALUES = 16 * 3


def _label_files(folder: Path) -> list[Path]:
    with os.scandir(folder) as it:
        names = [e.name for e in it if e.name.endswith(".txt") and e.is_file()]
    return [folder / n for n in sorted(names, key=natural_key)]


def _is_label_file(path: Path) -> bool:
    try:
        with open(path) as fh:
            first = fh.readline().split()
    except (OSError, UnicodeDecodeError):
        return False
    return len(first) == 1 + _VALUES and first[0].lower().endswith(".png")


def looks_like_icvl(path: str | Path) -> bool:
    """Cheap check: a label ``.txt`` file, or a folder with ``Depth/`` and a label ``.txt`` file."""
    path = Path(path)
    if path.is_file():
        return path.suffix == ".txt" and _is_label_file(path)
    if not (path / "Depth").is_dir():
        return False
    return any(_is_label_file(f) for f in _label_files(path))


class ICVLSequence(FileListSequence):
    """ICVL frames listed in one label file, in the file's order."""

    format = "icvl"

    def __init__(
        self,
        path: str | Path,
        intrinsics: CameraIntrinsics | None = None,
        depth_scale_mm: float | None = None,
    ):
        path = Path(path)
        if path.is_dir():
            candidates = [f for f in _label_files(path) if _is_label_file(f)]
            if not candidates:
                raise DatasetError(
                    f"{path}: no ICVL label file (lines 'file.png u1 v1 d1 ... u16 v16 d16') found"
                )
            label_file = candidates[0]
        elif path.is_file():
            label_file = path
        else:
            raise DatasetError(f"{path}: no such file or folder")
        root = label_file.parent
        names, uvd = read_icvl_labels(label_file)
        depth_dir = root / "Depth"
        if depth_dir.is_dir() and not names[0].startswith("Depth/"):
            self._base = depth_dir
        else:
            self._base = root
        self._files = names
        self._uvd = uvd
        self.label_file = label_file
        self.depth_scale_mm = 1.0 if depth_scale_mm is None else float(depth_scale_mm)
        if not self.depth_scale_mm > 0:
            raise DatasetError(f"{path}: depth_scale_mm must be > 0, got {depth_scale_mm}")
        super().__init__(root, intrinsics or ICVL_CAMERA, ICVL16)

    def depth(self, index: int) -> np.ndarray:
        index, path, shape = self._frame_file(index)
        return read_png16(path, index, shape, self.depth_scale_mm)

    def _load_ground_truth(self) -> GroundTruth:
        """Joints ``(N, 16, 3)`` mm in the OpenCV frame, back-projected from (u, v, d) labels."""
        return GroundTruth(self.camera.backproject(self._uvd[..., :2], self._uvd[..., 2]))


def read_icvl_labels(path: Path) -> tuple[list[str], np.ndarray]:
    """Parse an ICVL label file: file names and ``(N, 16, 3)`` (u px, v px, d mm)."""
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path}: cannot read label file: {exc}") from exc
    names: list[str] = []
    rows: list[list[str]] = []
    for i, line in enumerate(lines):
        tokens = line.split()
        if not tokens:
            continue
        if len(tokens) != 1 + _VALUES:
            raise DatasetError(
                f"{path}: line {i + 1}: {len(tokens) - 1} values after the file name, expected "
                f"{_VALUES} (16 joints x (u, v, d))"
            )
        names.append(tokens[0])
        rows.append(tokens[1:])
    if not names:
        raise DatasetError(f"{path}: label file has no frames")
    try:
        uvd = np.array(rows, dtype=np.float64).reshape(-1, 16, 3)
    except ValueError:
        raise DatasetError(f"{path}: non-numeric label value") from None
    bad = ~np.all(np.isfinite(uvd.reshape(len(uvd), -1)), axis=1)
    if bad.any():
        i = int(np.argmax(bad))
        raise DatasetError(f"{path}: frame {i} ({names[i]}): NaN/inf label value")
    return names, uvd
