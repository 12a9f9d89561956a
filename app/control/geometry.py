"""Scene geometry of one frame in the annotation view: pure numpy, no viser.

The scene is in **metres, centred on the hand**: a camera-frame point ``p_mm`` (OpenCV: x right,
y down, z forward) sits at ``(p_mm - centre_mm) / 1000`` in the scene. Centring keeps viser's
float16 point clouds precise (spacing ~0.05 mm within 0.1 m of the origin).

The depth image is shown as a plane at camera depth ``plane_z_mm`` (behind the hand, so the cloud
is in front of it), scaled so that the pixel ``(u, v)`` sits exactly where the camera ray through
``(u, v)`` meets the plane: seen from the sensor position the image and the cloud line up.
viser draws an image node in its local x-y plane with row 0 at local -y and column 0 at local -x,
so with an identity orientation local ``(x, y)`` = OpenCV ``(X, Y)`` on the plane.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from handanno_core.camera import CameraIntrinsics
from handanno_core.crops import DEFAULT_CROP
from handanno_core.sampling import depth_at

#: at most this many cloud points are sent per frame.
MAX_CLOUD_POINTS = 50_000

# A perceptually ordered colour ramp (near = warm/yellow, far = dark blue), RGB 0..255.
_RAMP = np.array(
    [
        [253, 231, 37],
        [94, 201, 98],
        [33, 145, 140],
        [59, 82, 139],
        [68, 1, 84],
    ],
    dtype=np.float64,
)
INVALID_RGB = (40, 40, 40)


def colormap(t: np.ndarray) -> np.ndarray:
    """Map ``t`` in [0, 1] (any shape) to uint8 RGB ``(..., 3)``; 0 = near (bright), 1 = far."""
    t = np.clip(np.nan_to_num(np.asarray(t, dtype=np.float64), nan=1.0), 0.0, 1.0)
    x = t * (len(_RAMP) - 1)
    i = np.minimum(x.astype(np.int64), len(_RAMP) - 2)
    f = (x - i)[..., None]
    return (_RAMP[i] * (1 - f) + _RAMP[i + 1] * f).astype(np.uint8)


@dataclass
class FrameGeometry:
    """Everything the view needs to draw one frame and to map clicks back to pixels / mm.

    ``centre_mm`` (3,): hand centre (scene origin). ``cloud_mm`` (M,3): hand points, M <= 50k.
    ``plane_z_mm``: camera depth of the image plane.
    """

    camera: CameraIntrinsics
    centre_mm: np.ndarray
    plane_z_mm: float
    cloud_mm: np.ndarray = field(repr=False)
    cloud_rgb: np.ndarray = field(repr=False)
    image_rgb: np.ndarray = field(repr=False)

    # ------------------------------------------------------------------ scene <-> camera frame
    def to_scene(self, xyz_mm: np.ndarray) -> np.ndarray:
        """Camera-frame mm ``(..., 3)`` -> scene metres ``(..., 3)``."""
        return (np.asarray(xyz_mm, dtype=np.float64) - self.centre_mm) / 1000.0

    def from_scene(self, xyz_m: np.ndarray) -> np.ndarray:
        """Scene metres ``(..., 3)`` -> camera-frame mm ``(..., 3)``."""
        return np.asarray(xyz_m, dtype=np.float64) * 1000.0 + self.centre_mm

    @property
    def sensor_position(self) -> np.ndarray:
        """The depth camera's optical centre in scene metres (3,)."""
        return self.to_scene(np.zeros(3))

    # ------------------------------------------------------------------ image plane
    @property
    def image_render_size(self) -> tuple[float, float]:
        """(render_width, render_height) of the image node in metres."""
        cam = self.camera
        return (
            cam.width * self.plane_z_mm / cam.fx / 1000.0,
            cam.height * self.plane_z_mm / cam.fy / 1000.0,
        )

    @property
    def image_position(self) -> np.ndarray:
        """Scene position (3,) of the image node's centre (continuous pixel ((W-1)/2, (H-1)/2))."""
        cam = self.camera
        mid = np.array([(cam.width - 1) / 2.0, (cam.height - 1) / 2.0])
        return self.pixel_to_scene(mid)

    def pixel_to_scene(self, uv_px: np.ndarray, offset_mm: float = 0.0) -> np.ndarray:
        """Pixels ``(..., 2)`` -> scene points ``(..., 3)`` on the image plane (moved ``offset_mm``
        towards the camera, e.g. to draw handles just in front of the image)."""
        uv = np.asarray(uv_px, dtype=np.float64)
        z = np.full(uv.shape[:-1], self.plane_z_mm - offset_mm)
        return self.to_scene(self.camera.backproject(uv, z))

    def ray_to_pixel(self, origin_m: np.ndarray, direction_m: np.ndarray) -> np.ndarray | None:
        """Intersect a scene ray with the image plane -> pixel (2,) (u, v), or None if it misses
        the plane (parallel, behind the origin) or lands outside the image."""
        o = self.from_scene(origin_m)
        d = np.asarray(direction_m, dtype=np.float64)
        if abs(d[2]) < 1e-12:
            return None
        t = (self.plane_z_mm - o[2]) / d[2]
        if t <= 0:
            return None
        uv = self.camera.project(o + t * d)
        if not np.all(np.isfinite(uv)):
            return None
        if not (
            -0.5 <= uv[0] <= self.camera.width - 0.5 and -0.5 <= uv[1] <= self.camera.height - 0.5
        ):
            return None
        return uv

    # ------------------------------------------------------------------ cloud picking
    def nearest_cloud_point(
        self, origin_m: np.ndarray, direction_m: np.ndarray, tolerance_rad: float = 0.015
    ) -> np.ndarray | None:
        """The cloud point (mm, (3,)) a click ray points at, or None.

        Candidates are points within ``tolerance_rad`` of the ray direction (seen from the ray
        origin, so the tolerance is a fixed size on screen); of those, the one nearest the
        camera along the ray wins (the visible surface)."""
        if len(self.cloud_mm) == 0:
            return None
        o = np.asarray(origin_m, dtype=np.float64)
        d = np.asarray(direction_m, dtype=np.float64)
        d = d / np.linalg.norm(d)
        rel = self.to_scene(self.cloud_mm) - o
        along = rel @ d
        perp = np.linalg.norm(rel - along[:, None] * d, axis=1)
        angle = np.arctan2(perp, np.maximum(along, 1e-9))
        ok = (along > 0) & (angle <= tolerance_rad)
        if not ok.any():
            return None
        idx = np.flatnonzero(ok)
        # Among candidates: nearest along the ray, preferring small angles (within 2 mm band).
        front = along[idx].min()
        band = idx[along[idx] <= front + 0.01]
        best = band[np.argmin(angle[band])]
        return self.cloud_mm[best].copy()


def build_frame_geometry(
    depth_mm: np.ndarray,
    camera: CameraIntrinsics,
    centre_mm: np.ndarray,
    *,
    cube_mm: float = DEFAULT_CROP.cube_mm,
    max_points: int = MAX_CLOUD_POINTS,
) -> FrameGeometry:
    """Crop the hand's point cloud (points within a ``cube_mm`` cube around ``centre_mm``, at most
    ``max_points``, coloured by depth) and colour-map the whole depth image for the image plane.

    ``depth_mm`` (H, W) float mm, 0 = invalid. ``centre_mm`` (3,) mm; if not finite, the median of
    the valid points is used (and the origin if there are none).
    """
    depth = np.asarray(depth_mm, dtype=np.float32)
    centre = np.asarray(centre_mm, dtype=np.float64)
    valid = np.isfinite(depth) & (depth > 0)
    if not np.all(np.isfinite(centre)):
        if valid.any():
            pts_all, _ = camera.depth_to_points(depth)
            centre = np.median(pts_all, axis=0)
        else:
            centre = np.array([0.0, 0.0, 500.0])
    half = cube_mm / 2.0
    # Cheap pre-mask in the image: the cube's bounding box in pixels and depth band.
    near_mask = valid & (np.abs(depth - centre[2]) <= half)
    pts, _ = camera.depth_to_points(depth, near_mask)
    inside = np.all(np.abs(pts - centre) <= half, axis=1)
    pts = pts[inside]
    if len(pts) > max_points:
        step = int(np.ceil(len(pts) / max_points))
        pts = pts[::step]
    t = (pts[:, 2] - (centre[2] - half)) / cube_mm
    cloud_rgb = colormap(t)
    # Depth image: near..far around the hand; background beyond is still visible but dark.
    lo, hi = centre[2] - half, centre[2] + 2.5 * half
    image = colormap((depth - lo) / (hi - lo))
    image[~valid] = INVALID_RGB
    return FrameGeometry(
        camera=camera,
        centre_mm=centre,
        plane_z_mm=float(centre[2] + half + 20.0),
        cloud_mm=pts,
        cloud_rgb=cloud_rgb,
        image_rgb=image,
    )


def empty_geometry(camera: CameraIntrinsics, centre_mm: np.ndarray | None = None) -> FrameGeometry:
    """Geometry of a frame without depth: no points, a blank image (the view shows a message)."""
    centre = np.array([0.0, 0.0, 500.0]) if centre_mm is None else np.asarray(centre_mm, float)
    image = np.empty((camera.height, camera.width, 3), np.uint8)
    image[:] = INVALID_RGB
    return FrameGeometry(
        camera=camera,
        centre_mm=centre,
        plane_z_mm=float(centre[2] + 130.0),
        cloud_mm=np.zeros((0, 3)),
        cloud_rgb=np.zeros((0, 3), np.uint8),
        image_rgb=image,
    )


def surface_under(depth_mm: np.ndarray, uv_px: np.ndarray) -> np.ndarray:
    """``(P,)`` mm: the depth pixel under each point ``uv_px (P, 2)`` px of ``depth_mm (H, W)``,
    points off the image clamped onto its border; NaN where that pixel has no depth (the app's
    display lookup: :func:`handanno_core.sampling.depth_at` without a neighbourhood)."""
    h, w = np.shape(depth_mm)
    uv = np.clip(np.asarray(uv_px, dtype=np.float64), 0, [w - 1, h - 1])
    return depth_at(depth_mm, uv, window=0, near_px=0)


#: joints behind the observed surface are drawn this far in front of it
SURFACE_MARGIN_MM = 6.0


def pull_in_front_of_surface(
    joints_mm: np.ndarray, depth_mm: np.ndarray | None, camera: CameraIntrinsics
) -> np.ndarray:
    """Joints ``(J, 3)`` mm for display: each joint behind the observed surface is moved along its
    camera ray to ``SURFACE_MARGIN_MM`` in front of it, so the point cloud never hides it. Seen
    from the sensor it is exactly where it projects. Drags keep the offset
    (new joint = drop point + (true - drawn))."""
    out = np.array(joints_mm, dtype=np.float64)
    if depth_mm is None:
        return out
    ok = np.all(np.isfinite(out), axis=1) & (out[:, 2] > 0)
    if not ok.any():
        return out
    surface = surface_under(depth_mm, camera.project(out[ok]))
    z = out[ok, 2]
    with np.errstate(invalid="ignore"):
        pull = np.isfinite(surface) & (z > surface - SURFACE_MARGIN_MM)
    out[ok] *= np.where(pull, (surface - SURFACE_MARGIN_MM) / z, 1.0)[:, None]
    return out
