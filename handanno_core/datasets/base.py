"""The depth-sequence interface every reader implements.

A :class:`DepthSequence` is lazy: opening it reads only what is needed to know the frame count and
the camera; ``depth(i)`` reads one frame. Depth maps are ``(H, W)`` float32 in mm, 0 = no
measurement, in the OpenCV camera frame (readers convert other conventions once).

Ground truth, when a format has it, is exposed only through ``sequence.ground_truth`` so the
pipeline cannot touch it by accident: evaluation and the simulated annotator take it explicitly.
"""

from __future__ import annotations

import abc
import re
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ..camera import CameraIntrinsics
from ..skeleton import Skeleton


class DatasetError(ValueError):
    """A dataset cannot be opened: names the path and what is wrong."""


class FrameError(ValueError):
    """One frame is missing or corrupt. ``str()`` names the file, the frame and the problem."""

    def __init__(self, path: str | Path, frame: int, problem: str):
        self.path = str(path)
        self.frame = int(frame)
        self.problem = problem
        super().__init__(f"{self.path} (frame {self.frame}): {problem}")


@dataclass
class GroundTruth:
    """Ground-truth joints, kept apart from the depth. ``joints_mm``: ``(N, J, 3)`` camera frame."""

    joints_mm: np.ndarray

    def __post_init__(self) -> None:
        if self.joints_mm.ndim != 3 or self.joints_mm.shape[-1] != 3:
            raise ValueError(f"ground truth must be (N, J, 3), got {self.joints_mm.shape}")


@dataclass
class BadFrameReport:
    """Frames skipped while iterating, with the reason for each."""

    errors: list[FrameError] = field(default_factory=list)

    @property
    def frames(self) -> list[int]:
        return [e.frame for e in self.errors]

    def summary(self) -> str:
        if not self.errors:
            return "all frames read"
        lines = [f"{len(self.errors)} bad frame(s) skipped:"]
        lines += [f"  {e}" for e in self.errors[:20]]
        if len(self.errors) > 20:
            lines.append(f"  ... and {len(self.errors) - 20} more")
        return "\n".join(lines)


def validate_depth(
    depth: np.ndarray, path: str | Path, frame: int, shape: tuple[int, int]
) -> np.ndarray:
    """Check a decoded depth map; return it as float32 mm or raise :class:`FrameError`."""
    if depth.shape != shape:
        raise FrameError(path, frame, f"depth has shape {depth.shape}, expected {shape}")
    depth = depth.astype(np.float32, copy=False)
    if not np.all(np.isfinite(depth)):
        raise FrameError(path, frame, f"{int(np.sum(~np.isfinite(depth)))} NaN/inf depth values")
    if np.any(depth < 0):
        raise FrameError(path, frame, f"{int(np.sum(depth < 0))} negative depth values")
    return depth


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def check_frame_header(path: str | Path, frame: int, shape: tuple[int, int]) -> None:
    """Refuse a PNG or ``.npy`` frame whose header size is not ``shape`` = (H, W), *before* decoding.

    A 0.5 MB PNG can declare 16000 x 16000 pixels (1.5 GB decoded); the header says so in 24 bytes.
    Other files pass (their readers check the decoded shape). Raises :class:`FrameError`.
    """
    path = Path(path)
    try:
        if path.suffix.lower() == ".npy":
            size = np.load(path, mmap_mode="r", allow_pickle=False).shape  # header only
        else:
            with open(path, "rb") as f:
                head = f.read(24)
            if head[:8] != _PNG_SIGNATURE or head[12:16] != b"IHDR":
                return
            size = (int.from_bytes(head[20:24], "big"), int.from_bytes(head[16:20], "big"))
    except FileNotFoundError:
        raise FrameError(path, frame, "file missing") from None
    except (OSError, ValueError, EOFError) as exc:
        raise FrameError(
            path,
            frame,
            f"cannot read the header: {str(exc).splitlines()[0] if str(exc) else exc!r}",
        ) from exc
    if tuple(size[:2]) != tuple(shape) or len(size) not in (2, 3):
        raise FrameError(
            path,
            frame,
            f"depth has shape {tuple(size)}, expected {tuple(shape)} "
            "(from the file header; refused before decoding)",
        )


def read_npy(path: Path, index: int, shape: tuple[int, int]) -> np.ndarray:
    """The raw array of a ``.npy`` depth frame: its header is checked against ``shape`` before
    loading; :class:`FrameError` if unreadable."""
    check_frame_header(path, index, shape)  # before loading: the header states the size
    try:
        return np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise FrameError(path, index, f"cannot read .npy: {exc}") from exc


def read_png16(path: Path, index: int, shape: tuple[int, int], scale: float) -> np.ndarray:
    """Read a single-channel 16-bit PNG as ``(H, W)`` float32 mm (value x ``scale``)."""
    if not path.is_file():
        raise FrameError(path, index, "file missing")
    check_frame_header(path, index, shape)  # before decoding: a tiny PNG can declare gigapixels
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise FrameError(path, index, "unreadable image (not a valid PNG?)")
    if image.ndim != 2 or image.dtype != np.uint16:
        raise FrameError(
            path,
            index,
            f"expected a single-channel 16-bit PNG, got shape {image.shape} dtype {image.dtype}",
        )
    depth = image.astype(np.float32)
    if scale != 1.0:
        depth *= np.float32(scale)
    return validate_depth(depth, path, index, shape)


class DepthSequence(abc.ABC):
    """A lazily read depth video with a camera, a skeleton layout and optional ground truth."""

    #: the format name as used by ``--format`` (``msra``, ``blender``, ``nyu``, ``icvl``, ``folder``).
    format: str = ""

    def __init__(self, path: str | Path, camera: CameraIntrinsics, skeleton: Skeleton):
        self.path = Path(path)
        self.camera = camera
        self.skeleton = skeleton

    @abc.abstractmethod
    def __len__(self) -> int: ...

    @abc.abstractmethod
    def depth(self, index: int) -> np.ndarray:
        """Depth of frame ``index`` as ``(H, W)`` float32 mm; raises :class:`FrameError` if bad."""

    @property
    def ground_truth(self) -> GroundTruth | None:
        """Ground-truth joints or None. Only evaluation and the simulated annotator may use it.

        Read by :meth:`_load_ground_truth` on first access and kept (a failed read is retried)."""
        try:
            return self._ground_truth
        except AttributeError:
            self._ground_truth: GroundTruth | None = self._load_ground_truth()
            return self._ground_truth

    def _load_ground_truth(self) -> GroundTruth | None:
        """Read the ground truth (readers override this); None where the dataset has none."""
        return None

    @property
    def sequence_breaks(self) -> list[int]:
        """Frame indices where a new, temporally unrelated sequence starts (frame 0 excluded)."""
        return []

    @property
    def frame_names(self) -> list[str] | None:
        """Optional per-frame file names (for export and messages)."""
        return None

    @property
    def hand_labels(self) -> list[str] | None:
        """Whose hand each sequence shows, when the layout says so: one label per sequence
        between :attr:`sequence_breaks` (``len(sequence_breaks) + 1``), else None (unknown)."""
        return None

    def _check_index(self, index: int) -> int:
        n = len(self)
        if not -n <= index < n:
            raise IndexError(f"{self.path}: frame {index} out of range (sequence has {n} frames)")
        return index % n

    def iter_depth(
        self, frames: np.ndarray | list[int] | None = None, report: BadFrameReport | None = None
    ) -> Iterator[tuple[int, np.ndarray]]:
        """Yield ``(index, depth)``; bad frames are recorded in ``report`` and skipped.

        Without a ``report`` the first bad frame raises.
        """
        indices = range(len(self)) if frames is None else frames
        for i in indices:
            try:
                yield int(i), self.depth(int(i))
            except FrameError as err:
                if report is None:
                    raise
                report.errors.append(err)

    def describe(self) -> str:
        gt = "with ground truth" if self.ground_truth is not None else "no ground truth"
        c = self.camera
        return (
            f"{self.format} sequence {self.path}: {len(self)} frames, {c.width}x{c.height} px, "
            f"f=({c.fx:g}, {c.fy:g}), skeleton {self.skeleton.name}, {gt}"
        )


_DIGITS = re.compile(r"(\d+)")
_LAST_NUMBER = re.compile(r"^(.*?)(\d+)(\D*)$")

#: a jump in the frame numbers of file names this many times the usual step is a break.
GAP_FACTOR = 5.0


class FileListSequence(DepthSequence):
    """A sequence with one depth file per frame: ``_files`` (names relative to ``_base``, default
    the sequence folder) in frame order."""

    _files: list[str]

    def __len__(self) -> int:
        return len(self._files)

    @property
    def frame_names(self) -> list[str]:
        return list(self._files)

    def _frame_file(self, index: int) -> tuple[int, Path, tuple[int, int]]:
        """``(index, path, (H, W))`` of frame ``index`` (negative counts from the end)."""
        index = self._check_index(index)
        base = getattr(self, "_base", self.path)
        return index, base / self._files[index], (self.camera.height, self.camera.width)


def segment_ids(n: int, breaks) -> np.ndarray:
    """``(N,)`` index of the sequence segment of each of ``n`` frames (a break starts a new
    segment; breaks outside ``1..n-1`` are ignored)."""
    starts = np.zeros(n, dtype=np.int64)
    for b in breaks or ():
        if 0 < int(b) < n:
            starts[int(b)] = 1
    return np.cumsum(starts)


def breaks_from_names(names: list[str], gap_factor: float = GAP_FACTOR) -> list[int]:
    """Sequence breaks read off ordered frame file names: a new recording starts at frame ``i``
    when the text around the last number of its stem differs from frame ``i - 1``'s
    (``take1_0007`` -> ``take2_0000``), or when that number does not increase, or increases by
    more than ``gap_factor`` times the median step (frame numbers ``0, 20, 40, 900, 920`` or
    millisecond timestamps with a pause). Names without a number give no breaks."""
    parts = []
    for name in names:
        stem = name.rsplit(".", 1)[0]
        m = _LAST_NUMBER.match(stem)
        if m is None:
            return []
        parts.append((m.group(1), int(m.group(2)), m.group(3)))
    if len(parts) < 2:
        return []
    num = np.array([p[1] for p in parts], dtype=np.float64)
    step = np.diff(num)
    same = np.array(
        [a[0] == b[0] and a[2] == b[2] for a, b in zip(parts[:-1], parts[1:], strict=True)]
    )
    pos = step[same & (step > 0)]
    usual = float(np.median(pos)) if pos.size else 1.0
    cut = ~same | (step <= 0) | (step > gap_factor * usual)
    return [int(i) + 1 for i in np.flatnonzero(cut)]


def read_breaks_file(path: str | Path, names: list[str] | None, frames: int) -> list[int]:
    """Frame indices where a new recording starts, from a text file: one entry per line, a frame
    index (0-based) or a frame file name; blank lines and ``#`` comments ignored. Raises
    :class:`DatasetError` naming the file and line on an entry that is not a frame."""
    path = Path(path)
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path}: cannot read the breaks file: {exc}") from exc
    index = {n: i for i, n in enumerate(names or [])}
    out: set[int] = set()
    for k, line in enumerate(lines, 1):
        entry = line.split("#", 1)[0].strip()
        if not entry:
            continue
        if entry in index:
            i = index[entry]
        elif entry.lstrip("-").isdigit():
            i = int(entry)
        else:
            raise DatasetError(
                f"{path} line {k}: {entry!r} is neither a frame index nor a frame file"
            )
        if not 0 <= i < frames:
            raise DatasetError(f"{path} line {k}: frame {i} out of range (0..{frames - 1})")
        if i > 0:
            out.add(i)
    return sorted(out)


def natural_key(name: str) -> tuple:
    """Sort key that orders embedded numbers numerically (``f2`` before ``f10``)."""
    return tuple(int(t) if t.isdigit() else t.lower() for t in _DIGITS.split(name))
