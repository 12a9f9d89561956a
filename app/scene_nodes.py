"""Scene nodes both views draw the same way: the hand's point cloud, one batched mesh per joint
set, and the skeleton's bone segments (viser handles; the geometry comes from geometry.py)."""

from __future__ import annotations

from typing import Any

import numpy as np
import trimesh

from handanno_core.cloud import clean_hand_cloud

from .geometry import FrameGeometry

#: unit sphere of the joint handles (scaled per instance to the joint radius)
UNIT_SPHERE = trimesh.creation.icosphere(subdivisions=2, radius=1.0)


def add_hand_cloud(scene: Any, name: str, *, visible: bool = True) -> Any:
    """An empty point cloud node; :func:`show_hand_cloud` fills it per frame."""
    return scene.add_point_cloud(
        name,
        points=np.zeros((1, 3), np.float32),
        colors=(0, 0, 0),
        point_size=0.002,
        point_shape="rounded",
        visible=visible,
    )


def show_hand_cloud(
    cloud: Any, geo: FrameGeometry, joints_mm: np.ndarray | None = None, skeleton: Any = None
) -> bool:
    """Assign ``geo``'s cloud (scene metres, depth colours) to ``cloud``, cleaned by
    :func:`handanno_core.cloud.clean_hand_cloud` (no flying pixels; with ``joints_mm`` ``(J, 3)``
    and ``skeleton``, nothing past the wrist plane); points about 1.6 px wide at the hand's
    depth. Returns whether the frame has any point (the caller sets visibility)."""
    keep, _ = clean_hand_cloud(geo.cloud_mm, geo.camera, joints_mm=joints_mm, skeleton=skeleton)
    pts, rgb = geo.cloud_mm[keep], geo.cloud_rgb[keep]
    has_cloud = len(pts) > 0
    cloud.points = geo.to_scene(pts if has_cloud else geo.centre_mm[None]).astype(np.float32)
    cloud.colors = rgb if has_cloud else np.zeros((1, 3), np.uint8)
    cloud.point_size = float(1.6 * geo.centre_mm[2] / geo.camera.fx / 1000.0)
    return has_cloud


def add_joint_meshes(
    scene: Any, name: str, mesh: trimesh.Trimesh, colours: np.ndarray, **kwargs: Any
) -> Any:
    """One batched mesh with an instance per joint (``colours`` ``(J, 3)`` uint8), all at the
    origin with scale 0 (hidden) until the view assigns positions and scales."""
    j = len(colours)
    return scene.add_batched_meshes_simple(
        name,
        vertices=mesh.vertices,
        faces=mesh.faces,
        batched_wxyzs=np.tile([1.0, 0.0, 0.0, 0.0], (j, 1)),
        batched_positions=np.zeros((j, 3)),
        batched_scales=np.zeros(j),
        batched_colors=colours,
        cast_shadow=False,
        receive_shadow=False,
        lod="off",
        **kwargs,
    )


def add_bones(
    scene: Any, name: str, bones: np.ndarray, colours: np.ndarray, *, visible: bool = True
) -> Any:
    """Line segments for ``bones`` ``(B, 2)`` (parent, child), coloured like the child joint."""
    return scene.add_line_segments(
        name,
        points=np.zeros((len(bones), 2, 3), np.float32),
        colors=np.repeat(colours[bones[:, 1]][:, None, :], 2, axis=1),
        thickness=3.0,
        thickness_units="screen",
        visible=visible,
    )
