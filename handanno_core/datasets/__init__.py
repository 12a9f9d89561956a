"""Depth-sequence readers. ``open_sequence`` auto-detects the format; see base.py for the interface.

Formats (``FORMATS``): ``msra`` (``%06d_depth.bin`` + ``joint.txt``), ``blender`` (``*depth*.npy`` in
metres + ``*anno_blender.txt``), ``nyu`` (RGB-packed ``depth_1_%07d.png`` + ``joint_data.mat``),
``icvl`` (16-bit PNG under ``Depth/`` + label ``.txt``), ``folder`` (16-bit PNG or ``.npy`` frames +
``intrinsics.json``). Every reader converts to the OpenCV frame and mm, and is lazy.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from ..camera import CameraIntrinsics
from .base import BadFrameReport, DatasetError, DepthSequence, FrameError, GroundTruth
from .blender import BlenderSequence, looks_like_blender
from .folder import FolderSequence, looks_like_folder
from .icvl import ICVLSequence, looks_like_icvl
from .msra import MSRASequence, looks_like_msra, write_msra_frame, write_msra_joints
from .nyu import NYUSequence, looks_like_nyu

#: format name (as used by ``--format``) -> reader class, in auto-detection order.
FORMATS: dict[str, type[DepthSequence]] = {
    "msra": MSRASequence,
    "blender": BlenderSequence,
    "nyu": NYUSequence,
    "icvl": ICVLSequence,
    "folder": FolderSequence,
}

_DETECTORS: dict[str, Callable[[Path], bool]] = {
    "msra": looks_like_msra,
    "blender": looks_like_blender,
    "nyu": looks_like_nyu,
    "icvl": looks_like_icvl,
    "folder": looks_like_folder,
}
_SCALED = {"icvl", "folder"}  # formats whose integer depth takes a depth_scale_mm


def detect_format(path: str | Path) -> str | None:
    """The first format (in ``FORMATS`` order) whose cheap file-name check matches, else None.

    A file: a ``.txt`` ICVL label file -> icvl; ``joint_data.mat`` -> nyu. A folder: ``*_depth.bin``
    (here or up to two levels below) -> msra; ``*anno_blender.txt`` / ``c00_<id>_depth*.npy`` ->
    blender; ``depth_<k>_%07d.png`` (here or in ``train/``) -> nyu; ``Depth/`` + a label ``.txt`` ->
    icvl; any ``.png`` / ``.npy`` -> folder.
    """
    path = Path(path)
    if path.is_file():
        if path.name == "joint_data.mat":
            return "nyu"
        return "icvl" if looks_like_icvl(path) else None
    if not path.is_dir():
        return None
    for name, check in _DETECTORS.items():
        try:
            if check(path):
                return name
        except OSError:
            continue
    return None


def open_sequence(
    path: str | Path,
    format: str | None = None,
    intrinsics: CameraIntrinsics | None = None,
    depth_scale_mm: float | None = None,
) -> DepthSequence:
    """Open a depth sequence lazily (reads no frame); ``format`` overrides auto-detection.

    ``intrinsics`` replaces the format's default / stored camera. ``depth_scale_mm`` (mm per unit of
    a 16-bit PNG) applies to ``folder`` and ``icvl`` only; other formats raise if it is not 1.
    Raises :class:`DatasetError` naming the path when the format is unknown or undetectable.
    """
    path = Path(path)
    known = ", ".join(FORMATS)
    if not path.exists():
        raise DatasetError(f"{path}: no such file or folder")
    if format is None:
        format = detect_format(path)
        if format is None:
            raise DatasetError(
                f"{path}: cannot detect the dataset format (known formats: {known}); pass format="
            )
    format = format.lower()
    if format not in FORMATS:
        raise DatasetError(f"{path}: unknown format {format!r} (known formats: {known})")
    cls = FORMATS[format]
    if format in _SCALED:
        return cls(path, intrinsics=intrinsics, depth_scale_mm=depth_scale_mm)
    if depth_scale_mm is not None and float(depth_scale_mm) != 1.0:
        raise DatasetError(
            f"{path}: depth_scale_mm applies to the {' and '.join(sorted(_SCALED))} formats, "
            f"not {format} (whose files have a fixed unit)"
        )
    return cls(path, intrinsics=intrinsics)


__all__ = [
    "FORMATS",
    "BadFrameReport",
    "BlenderSequence",
    "DatasetError",
    "DepthSequence",
    "FolderSequence",
    "FrameError",
    "GroundTruth",
    "ICVLSequence",
    "MSRASequence",
    "NYUSequence",
    "detect_format",
    "open_sequence",
    "write_msra_frame",
    "write_msra_joints",
]
