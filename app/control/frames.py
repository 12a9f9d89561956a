"""Per-frame data for the views: depth, hand centre and scene geometry, cached (LRU, thread-safe).

A frame whose depth cannot be read (missing or corrupt file) is not an error for the app: it comes
back with ``error`` set and an empty geometry, and the view shows the message instead.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from handanno_core.session import CROPS_META_FILE, Session

from .geometry import FrameGeometry, build_frame_geometry, empty_geometry


@dataclass
class FrameData:
    frame: int
    depth: np.ndarray | None  # (H, W) float32 mm, None if unreadable
    geometry: FrameGeometry
    error: str | None = None


class FrameStore:
    """Loads frames of a session's sequence on demand and keeps the last ``capacity`` of them."""

    def __init__(self, session: Session, capacity: int = 16):
        self.session = session
        self.capacity = capacity
        self._cache: OrderedDict[int, FrameData] = OrderedDict()
        self._lock = threading.Lock()
        self._centres = self._load_centres()
        self._box_cubes = self._load_box_cubes()
        self._names: list[str] | None = None

    def _load_centres(self) -> np.ndarray | None:
        """Hand centres (N,3) mm from the crop cache, if the pipeline computed them."""
        path = self.session.folder / CROPS_META_FILE
        if not path.exists():
            return None
        try:
            with np.load(path) as meta:
                for key in ("centres_mm", "centres"):
                    if key in meta.files:
                        c = np.asarray(meta[key], dtype=np.float64)
                        if c.shape == (self.session.num_frames, 3):
                            return c
        except (OSError, ValueError):
            return None
        return None

    def _load_box_cubes(self) -> np.ndarray | None:
        """Each frame's own crop cube in x, y (N,) mm from the crop cache (a frame whose hand did
        not fit the session's cube has a larger one), if the pipeline stored them."""
        path = self.session.folder / CROPS_META_FILE
        try:
            with np.load(path) as meta:
                if "box_cubes_mm" in meta.files:
                    c = np.asarray(meta["box_cubes_mm"], dtype=np.float64)
                    if c.shape == (self.session.num_frames,):
                        return c
        except (OSError, ValueError):
            return None
        return None

    def cube_of(self, frame: int) -> float:
        """The cube (mm) the frame's hand cloud is cut at: the session's, or the frame's own
        larger crop box."""
        cube = float(self.session.model.settings.cube_mm)
        if self._box_cubes is not None and np.isfinite(self._box_cubes[frame]):
            cube = max(cube, float(self._box_cubes[frame]))
        return cube

    def source_name(self, frame: int) -> str | None:
        """The dataset's name of ``frame``'s depth file (``sequence.frame_names``, relative to the
        dataset folder), None where the format names none or the dataset cannot be opened."""
        if self._names is None:
            try:
                self._names = list(self.session.open_sequence().frame_names or [])
            except Exception:  # SessionError, OSError: the panel simply shows no name
                self._names = []
        return self._names[frame] if 0 <= frame < len(self._names) else None

    def centre_of(self, frame: int, depth: np.ndarray) -> np.ndarray:
        if self._centres is not None and np.all(np.isfinite(self._centres[frame])):
            return self._centres[frame]
        from handanno_core.crops import locate_hand

        return locate_hand(depth, self.session.camera, cube_mm=self.session.model.settings.cube_mm)

    def get(self, frame: int) -> FrameData:
        with self._lock:
            data = self._cache.get(frame)
            if data is not None:
                self._cache.move_to_end(frame)
                return data
        data = self._load(frame)
        with self._lock:
            self._cache[frame] = data
            while len(self._cache) > self.capacity:
                self._cache.popitem(last=False)
        return data

    def _load(self, frame: int) -> FrameData:
        camera = self.session.camera
        try:
            depth = np.asarray(self.session.open_sequence().depth(frame), dtype=np.float32)
        except Exception as exc:  # FrameError, SessionError, OSError: show, don't break
            return FrameData(
                frame, None, empty_geometry(camera), error=f"frame {frame}: no depth ({exc})"
            )
        if depth.shape != (camera.height, camera.width):
            return FrameData(
                frame,
                None,
                empty_geometry(camera),
                error=f"frame {frame}: depth is {depth.shape}, camera expects {(camera.height, camera.width)}",
            )
        centre = self.centre_of(frame, depth)
        geometry = build_frame_geometry(depth, camera, centre, cube_mm=self.cube_of(frame))
        error = None if len(geometry.cloud_mm) else f"frame {frame}: no hand found in the depth map"
        return FrameData(frame, depth, geometry, error)
