"""MSRA-2015 hand-gesture layout (Sun et al., CVPR 2015): ``%06d_depth.bin`` + ``joint.txt``.

A gesture folder holds ``%06d_depth.bin`` frames and ``joint.txt``; a dataset folder may hold many
gesture folders (``P0/1``, ``P0/2`` ... or ``1/``, ``2/`` ...), which open as **one** sequence with a
``sequence_breaks`` entry at the first frame of every gesture after the first. With subject folders
(``P0/1``) the subject folder is each gesture's hand label (``hand_labels``): one person's hand.

``.bin`` frame: six little-endian int32 ``(img_width, img_height, left, top, right, bottom)`` then
float32 depth (mm) of the box ``[left, right) x [top, bottom)``, row-major; the rest of the image is 0.

``joint.txt``: first line N, then N lines of 63 floats = 21 joints x (x, y, z) mm in the dataset's
convention (y up, z negative, i.e. the camera looks down -z). The reader converts to the OpenCV
frame once, ``(x, y, z) -> (x, -y, -z)``; :func:`write_msra_joints` converts back.

An optional ``camera.json`` (:class:`~handanno_core.camera.CameraIntrinsics`) in the dataset folder
(or in the first gesture folder) overrides the default :data:`~handanno_core.camera.MSRA_CAMERA`.

Opening is lazy: frames are counted by listing file names; ``joint.txt`` is parsed only when
``ground_truth`` is first accessed; ``depth(i)`` reads one file.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np

from ..camera import MSRA_CAMERA, CameraIntrinsics
from ..skeleton import MSRA21
from .base import DatasetError, DepthSequence, FrameError, GroundTruth, natural_key, validate_depth

FRAME_SUFFIX = "_depth.bin"
JOINT_FILE = "joint.txt"
CAMERA_FILE = "camera.json"
#: the 17 gesture folders of every MSRA-2015 subject (``P0`` ... ``P8``), in the dataset's order
GESTURES = (
    "1",
    "2",
    "3",
    "4",
    "5",
    "6",
    "7",
    "8",
    "9",
    "I",
    "IP",
    "L",
    "MP",
    "RP",
    "T",
    "TIP",
    "Y",
)
_HEADER = np.dtype("<i4")
_DEPTH = np.dtype("<f4")
#: folders below the dataset root searched for gesture folders (root/P0/1 is depth 2).
_MAX_NESTING = 3


def _frame_numbers(folder: str) -> np.ndarray:
    """Sorted frame numbers of the ``%06d_depth.bin`` files directly in ``folder`` (file listing only)."""
    numbers = []
    with os.scandir(folder) as it:
        for entry in it:
            name = entry.name
            if name.endswith(FRAME_SUFFIX):
                stem = name[: -len(FRAME_SUFFIX)]
                if stem.isdigit():
                    numbers.append(int(stem))
    return np.sort(np.asarray(numbers, dtype=np.int64))


def _gesture_folders(root: str, depth: int = 0) -> list[str]:
    """Folders (root first, then sub-folders in natural order) that directly contain frames."""
    found = []
    subdirs = []
    has_frames = False
    with os.scandir(root) as it:
        for entry in it:
            if entry.is_dir():
                subdirs.append(entry.name)
            elif not has_frames and entry.name.endswith(FRAME_SUFFIX):
                has_frames = entry.name[: -len(FRAME_SUFFIX)].isdigit()
    if has_frames:
        found.append(root)
    if depth < _MAX_NESTING:
        for name in sorted(subdirs, key=natural_key):
            found += _gesture_folders(os.path.join(root, name), depth + 1)
    return found


def looks_like_msra(path: str | Path) -> bool:
    """Cheap format check: ``path`` is a folder with ``*_depth.bin`` frames in it or below it."""
    path = Path(path)
    if not path.is_dir():
        return False
    try:
        return bool(_gesture_folders(str(path), depth=max(0, _MAX_NESTING - 2)))
    except OSError:
        return False


class MSRASequence(DepthSequence):
    """An MSRA-2015 gesture folder, or a folder of gesture folders read as one sequence.

    Parameters
    ----------
    path : folder in MSRA layout (see module docstring).
    intrinsics : camera; default ``camera.json`` if present, else ``MSRA_CAMERA`` (320x240).
    """

    format = "msra"

    def __init__(self, path: str | Path, intrinsics: CameraIntrinsics | None = None):
        root = Path(path)
        if not root.is_dir():
            raise DatasetError(
                f"{root}: not a folder (MSRA layout needs a folder of *_depth.bin files)"
            )
        try:
            folders = _gesture_folders(str(root))
        except OSError as exc:
            raise DatasetError(f"{root}: cannot list folder: {exc}") from exc
        if not folders:
            raise DatasetError(f"{root}: no %06d_depth.bin frames found (MSRA layout)")
        self._folders = folders
        self._numbers = [_frame_numbers(f) for f in folders]
        counts = np.array([len(n) for n in self._numbers], dtype=np.int64)
        #: first frame index of every gesture folder, plus the total at the end.
        self._offsets = np.concatenate([[0], np.cumsum(counts)])
        if intrinsics is None:
            intrinsics = self._find_camera(root, folders)
        super().__init__(root, intrinsics, MSRA21)

    @staticmethod
    def _find_camera(root: Path, folders: list[str]) -> CameraIntrinsics:
        for candidate in (root / CAMERA_FILE, Path(folders[0]) / CAMERA_FILE):
            if candidate.is_file():
                try:
                    return CameraIntrinsics.from_json(candidate)
                except ValueError as exc:
                    raise DatasetError(str(exc)) from exc
        return MSRA_CAMERA

    # ------------------------------------------------------------------ interface
    def __len__(self) -> int:
        return int(self._offsets[-1])

    @property
    def sequence_breaks(self) -> list[int]:
        return [int(o) for o in self._offsets[1:-1] if 0 < o < len(self)]

    @property
    def hand_labels(self) -> list[str] | None:
        """The subject folder of every gesture folder (``P0`` of ``P0/1``) when the dataset
        folder holds subject folders of gesture folders; None otherwise (one hand)."""
        rel = [Path(os.path.relpath(f, self.path)).parts for f in self._folders]
        if len(rel) < 2 or any(len(r) < 2 for r in rel):
            return None
        return [r[0] for r in rel]

    def frame_path(self, index: int) -> Path:
        """Path of frame ``index``'s ``.bin`` file."""
        index = self._check_index(index)
        g = int(np.searchsorted(self._offsets, index, side="right")) - 1
        number = int(self._numbers[g][index - self._offsets[g]])
        return Path(self._folders[g]) / f"{number:06d}{FRAME_SUFFIX}"

    @property
    def frame_names(self) -> list[str]:
        names = []
        for folder, numbers in zip(self._folders, self._numbers, strict=True):
            rel = os.path.relpath(folder, self.path)
            prefix = "" if rel == "." else rel + "/"
            names += [f"{prefix}{n:06d}{FRAME_SUFFIX}" for n in numbers]
        return names

    def depth(self, index: int) -> np.ndarray:
        index = self._check_index(index)
        path = self.frame_path(index)
        return read_msra_frame(path, index, (self.camera.height, self.camera.width))

    def _load_ground_truth(self) -> GroundTruth | None:
        """Joints ``(N, 21, 3)`` mm, OpenCV frame; parsed from ``joint.txt`` on first access.

        None when no gesture folder has a ``joint.txt``; :class:`DatasetError` when only some have
        one, or a file is malformed or its N disagrees with the frame count.
        """
        files = [Path(f) / JOINT_FILE for f in self._folders]
        present = [f.is_file() for f in files]
        if not any(present):
            return None
        if not all(present):
            missing = [str(f) for f, p in zip(files, present, strict=True) if not p]
            raise DatasetError(
                f"{self.path}: {len(missing)} gesture folder(s) lack {JOINT_FILE}, e.g. {missing[0]}"
            )
        parts = [
            read_msra_joints(f, expected_frames=len(n))
            for f, n in zip(files, self._numbers, strict=True)
        ]
        return GroundTruth(np.concatenate(parts, axis=0))


# ---------------------------------------------------------------------- reading
def read_msra_frame(path: str | Path, frame: int, shape: tuple[int, int]) -> np.ndarray:
    """Read one ``.bin`` frame into an ``(H, W)`` float32 mm depth map; :class:`FrameError` if bad.

    ``shape`` = (H, W) expected from the camera; the header's image size must match it.
    """
    try:
        with open(path, "rb") as fh:
            data = fh.read()
    except OSError as exc:
        raise FrameError(path, frame, f"cannot read file: {exc.strerror or exc}") from exc
    if len(data) < 24:
        raise FrameError(path, frame, f"truncated: {len(data)} bytes, the header alone needs 24")
    width, height, left, top, right, bottom = (int(v) for v in np.frombuffer(data, _HEADER, 6))
    h, w = shape
    if (width, height) != (w, h):
        raise FrameError(
            path, frame, f"header image size {width}x{height} differs from the camera's {w}x{h}"
        )
    if not (0 <= left < right <= width and 0 <= top < bottom <= height):
        raise FrameError(
            path,
            frame,
            f"bounding box left={left} top={top} right={right} bottom={bottom} is empty or "
            f"outside the {width}x{height} image",
        )
    box_h, box_w = bottom - top, right - left
    expected = 24 + 4 * box_h * box_w
    if len(data) != expected:
        raise FrameError(
            path,
            frame,
            f"wrong size: {len(data)} bytes, a {box_w}x{box_h} box needs {expected}"
            + (" (truncated)" if len(data) < expected else " (trailing bytes)"),
        )
    depth = np.zeros((h, w), dtype=np.float32)
    depth[top:bottom, left:right] = np.frombuffer(data, _DEPTH, box_h * box_w, 24).reshape(
        box_h, box_w
    )
    return validate_depth(depth, path, frame, shape)


def read_msra_joints(path: str | Path, expected_frames: int | None = None) -> np.ndarray:
    """Parse a ``joint.txt`` into ``(N, 21, 3)`` float64 mm in the OpenCV frame.

    Raises :class:`DatasetError` naming the file (and the line where possible) if malformed.
    """
    path = Path(path)
    try:
        with open(path) as fh:
            first = fh.readline()
            try:
                n = int(first.strip())
            except ValueError:
                raise DatasetError(
                    f"{path}: line 1 must be the frame count N, got {first.strip()[:40]!r}"
                ) from None
            if n < 0:
                raise DatasetError(f"{path}: line 1: negative frame count {n}")
            if expected_frames is not None and n != expected_frames:
                raise DatasetError(
                    f"{path}: line 1 says N={n} joint lines but the folder has "
                    f"{expected_frames} depth frames"
                )
            try:
                with warnings.catch_warnings():  # "input contained no data" -> checked below
                    warnings.simplefilter("ignore", UserWarning)
                    flat = np.loadtxt(fh, dtype=np.float64, ndmin=2)
            except ValueError:
                flat = None
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path}: cannot read joint file: {exc}") from exc
    if flat is None or (flat.size and flat.shape[1] != 63):
        _raise_bad_joint_line(path)
    if len(flat) != n:
        raise DatasetError(f"{path}: line 1 says N={n} frames but {len(flat)} joint lines follow")
    if n == 0:
        return np.zeros((0, 21, 3))
    joints = flat.reshape(n, 21, 3)
    if not np.all(np.isfinite(joints)):
        bad = int(np.argmax(~np.all(np.isfinite(flat), axis=1)))
        raise DatasetError(f"{path}: line {bad + 2} (frame {bad}): NaN/inf joint coordinates")
    joints[..., 1:] *= -1.0
    return joints


def _raise_bad_joint_line(path: Path) -> None:
    """Find and report the first malformed line (slow path, only on error)."""
    lines = path.read_text().split("\n")[1:]
    while lines and not lines[-1].strip():
        lines.pop()
    for i, line in enumerate(lines):
        tokens = line.split()
        if len(tokens) != 63:
            raise DatasetError(
                f"{path}: line {i + 2} (frame {i}): {len(tokens)} values, expected 63 (21 joints x 3)"
            )
        try:
            [float(t) for t in tokens]
        except ValueError:
            raise DatasetError(f"{path}: line {i + 2} (frame {i}): non-numeric value") from None
    raise DatasetError(f"{path}: malformed joint file")  # pragma: no cover


# ---------------------------------------------------------------------- writing
def write_msra_frame(path: str | Path, depth: np.ndarray) -> None:
    """Write an ``(H, W)`` float mm depth map (0 = invalid) as an MSRA ``.bin`` frame.

    The box is the tight bounding box of ``depth > 0``; an all-zero frame gets a 1x1 box of 0.
    """
    depth = np.asarray(depth)
    if depth.ndim != 2:
        raise ValueError(f"depth must be (H, W), got shape {depth.shape}")
    if not np.all(np.isfinite(depth)) or np.any(depth < 0):
        raise ValueError(f"{path}: depth must be finite and >= 0")
    h, w = depth.shape
    rows = np.flatnonzero(depth.any(axis=1))
    if rows.size:
        cols = np.flatnonzero(depth.any(axis=0))
        top, bottom, left, right = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
    else:
        top, bottom, left, right = 0, 1, 0, 1
    header = np.array([w, h, left, top, right, bottom], dtype=_HEADER)
    box = np.ascontiguousarray(depth[top:bottom, left:right], dtype=_DEPTH)
    with open(path, "wb") as fh:
        fh.write(header.tobytes())
        fh.write(box.tobytes())


def write_msra_joints(path: str | Path, joints_mm: np.ndarray) -> None:
    """Write joints ``(N, 21, 3)`` mm in the OpenCV frame as ``joint.txt`` (y up, z negative)."""
    joints = np.asarray(joints_mm, dtype=np.float64)
    if joints.ndim != 3 or joints.shape[1:] != (21, 3):
        raise ValueError(f"joints must be (N, 21, 3), got shape {joints.shape}")
    out = joints.copy()
    out[..., 1:] *= -1.0
    flat = out.reshape(len(out), 63)
    with open(path, "w") as fh:
        fh.write(f"{len(flat)}\n")
        if len(flat):
            np.savetxt(fh, flat, fmt="%.6f", delimiter=" ")


__all__ = [
    "MSRASequence",
    "looks_like_msra",
    "read_msra_frame",
    "read_msra_joints",
    "write_msra_frame",
    "write_msra_joints",
]
