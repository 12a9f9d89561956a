"""Pinhole camera: projection, back-projection and depth map -> point cloud.

Conventions (see DESIGN.md): millimetres in 3D, pixels in 2D, OpenCV camera frame
(x right, y down, z forward). Pixel (u, v) = (column, row); the centre of the top-left pixel is
(0, 0). Depth maps are float arrays in mm with 0 meaning "no measurement".
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from .fileio import read_json_object

#: Largest image side accepted (px). Depth sensors stay far below (Kinect v2 512x424, Azure Kinect
#: 1024x1024, RealSense 1280x720); the cap bounds a frame at 4096 x 4096 x 4 B = 64 MiB of
#: float32 before anything is allocated, whatever a camera file or an image header claims.
MAX_IMAGE_SIDE_PX = 4096
#: Largest focal length accepted (px): 100x the longest side; beyond that it is not a camera.
MAX_FOCAL_PX = 100.0 * MAX_IMAGE_SIDE_PX


class CameraIntrinsics(BaseModel):
    """Pinhole intrinsics in pixels; ``width``/``height`` are the image size in pixels.

    Refused (``ValueError`` saying which value): non-finite values, focal lengths outside
    (0, MAX_FOCAL_PX], a principal point farther than one image size outside the image, image
    sides above :data:`MAX_IMAGE_SIDE_PX`.
    """

    model_config = ConfigDict(frozen=True, allow_inf_nan=False)

    fx: float = Field(gt=0, le=MAX_FOCAL_PX)
    fy: float = Field(gt=0, le=MAX_FOCAL_PX)
    cx: float
    cy: float
    width: int = Field(gt=0, le=MAX_IMAGE_SIDE_PX)
    height: int = Field(gt=0, le=MAX_IMAGE_SIDE_PX)

    @model_validator(mode="after")
    def _principal_point_near_the_image(self) -> CameraIntrinsics:
        if not (
            -self.width <= self.cx <= 2 * self.width and -self.height <= self.cy <= 2 * self.height
        ):
            raise ValueError(
                f"principal point ({self.cx:g}, {self.cy:g}) lies far outside the "
                f"{self.width}x{self.height} image"
            )
        return self

    @classmethod
    def checked(cls, where: str, **values: float) -> CameraIntrinsics:
        """Build from user input; a bad value raises ``ValueError("<where>: <field>: <why>")``."""
        try:
            return cls(**values)
        except ValidationError as exc:
            raise ValueError(f"{where}: {_first_error(exc)}") from None

    # ------------------------------------------------------------------ projection
    def project(self, xyz_mm: np.ndarray) -> np.ndarray:
        """Project points ``(..., 3)`` in mm to pixels ``(..., 2)`` (u, v).

        Points at or behind the camera (z <= 0) project to NaN.
        """
        xyz = np.asarray(xyz_mm, dtype=np.float64)
        if xyz.shape[-1] != 3:
            raise ValueError(f"project expects (..., 3) points, got shape {xyz.shape}")
        z = xyz[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            safe_z = np.where(z > 0, z, np.nan)
            u = self.fx * xyz[..., 0] / safe_z + self.cx
            v = self.fy * xyz[..., 1] / safe_z + self.cy
        return np.stack([u, v], axis=-1)

    def on_image(self, uv_px: np.ndarray) -> np.ndarray:
        """``(...)`` bool: pixels ``(..., 2)`` (u, v) within ``[0, width - 1] x [0, height - 1]``,
        where a click on the image can land (NaN: False)."""
        uv = np.asarray(uv_px, dtype=np.float64)
        with np.errstate(invalid="ignore"):
            return (
                (uv[..., 0] >= 0)
                & (uv[..., 0] <= self.width - 1)
                & (uv[..., 1] >= 0)
                & (uv[..., 1] <= self.height - 1)
            )

    def onto_image(self, uv_px: np.ndarray) -> np.ndarray:
        """Pixels ``(..., 2)`` (u, v) clipped into ``[0, width - 1] x [0, height - 1]``: where a
        click at them lands (:meth:`on_image`)."""
        return np.clip(
            np.asarray(uv_px, dtype=np.float64), 0.0, [self.width - 1.0, self.height - 1.0]
        )

    def backproject(self, uv_px: np.ndarray, depth_mm: np.ndarray) -> np.ndarray:
        """Back-project pixels ``(..., 2)`` with depths ``(...)`` in mm to points ``(..., 3)`` in mm."""
        uv = np.asarray(uv_px, dtype=np.float64)
        z = np.asarray(depth_mm, dtype=np.float64)
        if uv.shape[-1] != 2:
            raise ValueError(f"backproject expects (..., 2) pixels, got shape {uv.shape}")
        if z.shape != uv.shape[:-1]:
            raise ValueError(f"depth shape {z.shape} does not match pixel shape {uv.shape[:-1]}")
        x = (uv[..., 0] - self.cx) * z / self.fx
        y = (uv[..., 1] - self.cy) * z / self.fy
        return np.stack([x, y, z], axis=-1)

    def projection_jacobian(self, xyz_mm: np.ndarray) -> np.ndarray:
        """d(u, v)/d(x, y, z) for points ``(..., 3)``: returns ``(..., 2, 3)`` in px/mm."""
        xyz = np.asarray(xyz_mm, dtype=np.float64)
        x, y, z = xyz[..., 0], xyz[..., 1], xyz[..., 2]
        inv_z = 1.0 / z
        jac = np.zeros(xyz.shape[:-1] + (2, 3))
        jac[..., 0, 0] = self.fx * inv_z
        jac[..., 0, 2] = -self.fx * x * inv_z**2
        jac[..., 1, 1] = self.fy * inv_z
        jac[..., 1, 2] = -self.fy * y * inv_z**2
        return jac

    # ------------------------------------------------------------------ depth maps
    def depth_to_points(
        self, depth_mm: np.ndarray, mask: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Valid pixels of a depth map ``(H, W)`` as points ``(M, 3)`` mm and pixels ``(M, 2)`` (u, v).

        A pixel is valid when its depth is finite and > 0 and, if given, ``mask`` is true there.
        """
        depth = np.asarray(depth_mm)
        if depth.ndim != 2:
            raise ValueError(f"depth map must be 2-D (H, W), got shape {depth.shape}")
        valid = np.isfinite(depth) & (depth > 0)
        if mask is not None:
            valid &= mask
        rows, cols = np.nonzero(valid)
        uv = np.stack([cols, rows], axis=-1).astype(np.float64)
        return self.backproject(uv, depth[rows, cols].astype(np.float64)), uv

    # ------------------------------------------------------------------ I/O
    @classmethod
    def from_json(cls, path: str | Path) -> CameraIntrinsics:
        """Read ``{"fx":..,"fy":..,"cx":..,"cy":..,"width":..,"height":..}`` (extra keys ignored)."""
        path = Path(path)
        data = read_json_object(path, "camera intrinsics")
        try:
            return cls.model_validate({k: data[k] for k in data if k in cls.model_fields})
        except ValidationError as exc:
            raise ValueError(f"{path}: invalid camera intrinsics: {_first_error(exc)}") from None

    def to_json(self, path: str | Path) -> None:
        Path(path).write_text(self.model_dump_json(indent=2))


def _first_error(exc: ValidationError) -> str:
    err = exc.errors()[0]
    loc = ".".join(str(x) for x in err.get("loc", ()))
    msg = str(err["msg"]).removeprefix("Value error, ")
    return f"{loc}: {msg} (got {err.get('input')!r})" if loc else msg


#: MSRA-2015 / ICVL sensor (Creative Interactive Gesture Camera), y flipped to our convention.
MSRA_CAMERA = CameraIntrinsics(fx=241.42, fy=241.42, cx=160.0, cy=120.0, width=320, height=240)
#: NYU hand dataset Kinect (y flipped to our convention).
NYU_CAMERA = CameraIntrinsics(fx=588.03, fy=587.07, cx=320.0, cy=240.0, width=640, height=480)
#: Intel RealSense SR305 frames in shared/data/real-sr305.
SR305_CAMERA = CameraIntrinsics(
    fx=476.007, fy=476.007, cx=313.683, cy=242.755, width=640, height=480
)
