"""The one set of 3D scene nodes of a browser, shared by the Annotate and Review panels.

Nodes (client-scoped, under ``/hand``, metres centred on the hand, see app/control/geometry.py):

* ``/hand/cloud`` - the hand's point cloud coloured by depth (not clickable in viser: clicks are
  snapped server-side from ``scene.on_click`` rays);
* ``/hand/image`` - the colour-mapped depth image on a plane behind the hand, lined up with the
  cloud from the sensor;
* ``/hand/handles2d`` - 2D annotations as flat rings on the image plane, wider than the joint
  spheres in front of them (draggable within the plane, grabbed by the visible band);
* ``/hand/joints`` - the placed (or shown) joints as ONE batched mesh, draggable in 3D;
* ``/hand/guesses`` - joints not placed yet where the live lift guesses them: small and faded,
  with no click or drag binding, so a click "through" a guess reaches what is behind it;
* ``/hand/bones`` - skeleton line segments; ``/hand/labels/<k>`` - joint labels.

The active panel (``ClientUI`` sets :attr:`HandScene.panel`) draws into the nodes with
:meth:`HandScene.draw` and receives clicks and drops (:class:`ScenePanel`). Joints behind the
observed surface are drawn pulled along their camera ray to just in front of it (so the cloud does
not hide them); one :class:`DragState` keeps a drag's grab offset and that display offset, so a
drop lands where the true joint should go. Frame changes assign new arrays to the handles;
nothing is recreated.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
import trimesh
import viser

from handanno_core.cloud import clean_hand_cloud
from handanno_core.session import Session

from ..control.frames import FrameData
from ..control.geometry import FrameGeometry, pull_in_front_of_surface
from .theme import JOINT_RADIUS_M, joint_colours, load_colours, short_name

ROOT = "/hand"
#: unit sphere of the joint handles (scaled per instance to the joint radius)
UNIT_SPHERE = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
#: 2D rings: from the sensor view each joint's sphere sits right in front of its ring, so the ring
#: is CLEARANCE times wider than the sphere's footprint on the plane (its band stays grabbable);
#: inner radius RING_INNER of the outer one
HANDLE2D_MIN_RADIUS_M = 0.004
HANDLE2D_CLEARANCE = 1.6
RING_INNER = 0.7
#: the selected joint's sphere is drawn this much larger
SELECTED_SCALE = 1.6
#: guessed (not placed) joints: radius relative to a placed joint's, and opacity
GUESS_SCALE = 0.5
GUESS_OPACITY = 0.45
#: occluded joints are drawn in their colour mixed with this grey (``occluded_mix`` of colour)
OCCLUDED_GREY = 110.0


class ScenePanel(Protocol):
    """What a panel does with the scene's pointer events (rays in scene metres)."""

    def on_image_click(self, origin: np.ndarray, direction: np.ndarray) -> None: ...
    def on_scene_click(self, origin: np.ndarray, direction: np.ndarray, shift: bool) -> None: ...
    def on_joint_click(
        self, k: int | None, origin: np.ndarray, direction: np.ndarray, modifier: str | None
    ) -> None: ...
    def can_drag(self, k: int) -> bool: ...
    def on_drop(self, k: int, xyz_mm: np.ndarray) -> None: ...
    def on_ring_drop(self, k: int, uv_px: np.ndarray) -> None: ...


@dataclass
class DragState:
    """One drag at a time: the joint, the grab offset (what is added to the pointer) and the
    offset from the drawn to the true position (added on the drop)."""

    joint: int | None = None
    grab: np.ndarray = field(default_factory=lambda: np.zeros(3))
    to_true: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def start(self, k: int, grab: np.ndarray, to_true: np.ndarray | None = None) -> None:
        self.joint = int(k)
        self.grab = np.asarray(grab, dtype=np.float64)
        self.to_true = np.zeros_like(self.grab) if to_true is None else np.asarray(to_true)

    def active(self, k: int | None) -> bool:
        return self.joint is not None and k == self.joint

    def update(self, pointer: np.ndarray) -> np.ndarray:
        """Where the grabbed thing is drawn for pointer position ``pointer``."""
        return np.asarray(pointer, dtype=np.float64) + self.grab

    def end(self, pointer: np.ndarray) -> tuple[int, np.ndarray]:
        """``(joint, true position)`` of the drop; the drag is over."""
        k, out = int(self.joint), self.update(pointer) + self.to_true  # type: ignore[arg-type]
        self.joint = None
        return k, out


@dataclass
class Drawing:
    """What a panel wants drawn: ``joints_mm`` (J, 3) true positions (NaN = none); ``placed`` and
    ``guessed`` (J,) masks; the selected joint; ``occluded`` (J,); 2D rings at ``uv_px`` (J, 2)
    where ``has_2d``; labels on or off; ``scale`` of every placed sphere."""

    joints_mm: np.ndarray
    placed: np.ndarray
    guessed: np.ndarray
    selected: int | None = None
    occluded: np.ndarray | None = None
    uv_px: np.ndarray | None = None
    has_2d: np.ndarray | None = None
    labels: bool = True
    scale: float = 1.0


def _joint_meshes(scene: Any, name: str, mesh: trimesh.Trimesh, colours: np.ndarray, **kw: Any):
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
        **kw,
    )


class HandScene:
    """One browser's scene nodes; see the module docstring."""

    def __init__(self, client: viser.ClientHandle, session: Session):
        self.client = client
        self.session = session
        self.skeleton = session.skeleton
        self.colours = load_colours()
        self.base_colours = joint_colours(self.skeleton.parent_array, self.colours)
        self.lock = threading.RLock()
        self.data: FrameData | None = None
        j = self.skeleton.num_joints
        #: (J, 3) true mm and drawn scene positions of the last draw
        self.true_mm = np.full((j, 3), np.nan)
        self.drawn = np.full((j, 3), np.nan)
        self.radii = np.zeros(j)
        self.true_uv = np.full((j, 2), np.nan)  # (J, 2) px centres of the drawn 2D rings
        self.drag = DragState()
        self.ring_drag = DragState()
        self.panel: ScenePanel | None = None
        self._build()

    # ------------------------------------------------------------------ nodes
    def _build(self) -> None:
        scene = self.client.scene
        scene.set_up_direction("-y")  # OpenCV camera frame: y down
        cam, j, colours = self.session.camera, self.skeleton.num_joints, self.base_colours
        self.cloud = scene.add_point_cloud(
            f"{ROOT}/cloud", np.zeros((1, 3), np.float32), (0, 0, 0), point_size=0.002,
            point_shape="rounded",
        )  # fmt: skip
        self.image = scene.add_image(
            f"{ROOT}/image", np.zeros((cam.height, cam.width, 3), np.uint8), render_width=0.3,
            render_height=0.2, format="jpeg", jpeg_quality=90, cast_shadow=False,
            receive_shadow=False,
        )  # fmt: skip
        ring = trimesh.creation.annulus(r_min=RING_INNER, r_max=1.0, height=0.05, sections=32)
        self.handles2d = _joint_meshes(scene, f"{ROOT}/handles2d", ring, colours)
        self.joints = _joint_meshes(scene, f"{ROOT}/joints", UNIT_SPHERE, colours)
        # no click/drag binding: viser raycasts only bound nodes, so guesses never catch a click
        self.guesses = _joint_meshes(
            scene, f"{ROOT}/guesses", UNIT_SPHERE, colours,
            batched_opacities=np.full(j, GUESS_OPACITY, np.float32),
        )  # fmt: skip
        bones = self.skeleton.bones
        self.bones = scene.add_line_segments(
            f"{ROOT}/bones", np.zeros((len(bones), 2, 3), np.float32),
            np.repeat(colours[bones[:, 1]][:, None, :], 2, axis=1), thickness=3.0,
            thickness_units="screen",
        )  # fmt: skip
        self.labels = [
            scene.add_label(
                f"{ROOT}/labels/{k}",
                short_name(self.skeleton.joint_names[k]),
                position=(0.0, 0.0, 0.0),
                visible=False,
                font_screen_scale=0.7,
                anchor="bottom-left",
            )  # fmt: skip
            for k in range(j)
        ]
        self._bind()

    def _bind(self) -> None:
        scene = self.client.scene

        def ray(event: Any) -> tuple[np.ndarray, np.ndarray]:
            return np.asarray(event.ray_origin), np.asarray(event.ray_direction)

        @self.image.on_click
        def _(event: viser.SceneNodePointerEvent) -> None:
            if event.modifier is None and self.panel is not None:
                self.panel.on_image_click(*ray(event))

        @self.handles2d.on_click
        def _(event: viser.SceneNodePointerEvent) -> None:
            # a press on a ring that does not become a drag is a click on the image under it
            if event.modifier is None and self.panel is not None:
                self.panel.on_image_click(*ray(event))

        @scene.on_click()
        def _(event: viser.SceneClickEvent) -> None:
            if self.panel is not None:
                self.panel.on_scene_click(*ray(event), False)

        @scene.on_click(modifier="shift")
        def _(event: viser.SceneClickEvent) -> None:
            if self.panel is not None:
                self.panel.on_scene_click(*ray(event), True)

        @self.joints.on_click
        def _(event: viser.SceneNodePointerEvent) -> None:
            if self.panel is not None:
                self.panel.on_joint_click(event.instance_index, *ray(event), event.modifier)

        @self.joints.on_drag("left")
        async def _(event: viser.SceneNodeDragEvent) -> None:
            self._on_joint_drag(event)

        @self.handles2d.on_drag("left")
        async def _(event: viser.SceneNodeDragEvent) -> None:
            self._on_ring_drag(event)

    # ------------------------------------------------------------------ frame and camera
    def show_frame(self, data: FrameData, wrist_mm: np.ndarray | None, *, image: bool) -> None:
        """Load ``data``'s cloud (:meth:`show_cloud`) and depth image into the nodes."""
        geo = data.geometry
        with self.lock, self.client.atomic():
            self.data = data
            self.show_cloud(data, wrist_mm)
            rw, rh = geo.image_render_size
            self.image.image = geo.image_rgb
            self.image.render_width = rw
            self.image.render_height = rh
            self.image.position = geo.image_position
            self.image.visible = image and data.depth is not None

    def show_cloud(self, data: FrameData, wrist_mm: np.ndarray | None) -> None:
        """Load ``data``'s cloud (``clean_hand_cloud``: cut at the plane of ``wrist_mm`` (J, 3))."""
        geo, sk = data.geometry, self.skeleton
        keep, _ = clean_hand_cloud(geo.cloud_mm, geo.camera, joints_mm=wrist_mm, skeleton=sk)
        pts, rgb = geo.cloud_mm[keep], geo.cloud_rgb[keep]
        with self.lock, self.client.atomic():
            shown = pts if len(pts) else geo.centre_mm[None]
            self.cloud.points = geo.to_scene(shown).astype(np.float32)
            self.cloud.colors = rgb if len(pts) else np.zeros((1, 3), np.uint8)
            self.cloud.point_size = float(1.6 * geo.centre_mm[2] / geo.camera.fx / 1000.0)
            self.cloud.visible = len(pts) > 0

    def show_image(self, visible: bool) -> None:
        self.image.visible = visible and self.data is not None and self.data.depth is not None

    def reset_camera(self) -> None:
        """Put the browser camera at the depth sensor (pixels line up with the cloud). On small
        images it looks square-on along the optical axis at the whole image; on large ones
        (>= 512 px wide) it looks at the hand and frames the hand's crop."""
        data = self.data
        if data is None:
            return
        geo = data.geometry
        cam = self.session.camera
        half = cam.height / 2.0 / cam.fy
        # square-on: along the optical axis, as the sensor sees the image
        look = np.asarray(geo.sensor_position) + np.array([0.0, 0.0, geo.plane_z_mm / 1000.0])
        if cam.width >= 512 and geo.centre_mm[2] > 0:  # large image: frame the hand's crop
            cube = self.session.model.settings.cube_mm
            half = min(half, 0.65 * cube / float(geo.centre_mm[2]))
            look = np.zeros(3)
        with self.client.atomic():
            self.client.camera.up_direction = (0.0, -1.0, 0.0)
            self.client.camera.fov = float(2.0 * np.arctan(half))
            self.client.camera.position = geo.sensor_position
            self.client.camera.look_at = tuple(float(x) for x in look)

    # ------------------------------------------------------------------ drawing
    def display_mm(self, joints_mm: np.ndarray) -> np.ndarray:
        """Joints behind the observed surface pulled along their camera ray to just in front of
        it (:func:`~app.control.geometry.pull_in_front_of_surface`)."""
        depth = None if self.data is None else self.data.depth
        return pull_in_front_of_surface(joints_mm, depth, self.session.camera)

    def to_scene(self, joints_mm: np.ndarray) -> np.ndarray:
        """(J, 3) scene positions where ``joints_mm`` are drawn (NaN rows stay NaN)."""
        if self.data is None:
            return np.full_like(np.asarray(joints_mm, dtype=np.float64), np.nan)
        return self.data.geometry.to_scene(self.display_mm(joints_mm))

    def draw(self, d: Drawing) -> None:
        """Assign joints, guesses, bones, labels and 2D rings from ``d``."""
        if self.data is None:
            return
        geo = self.data.geometry
        pos = self.to_scene(d.joints_mm)
        shown = np.all(np.isfinite(pos), axis=1)
        placed, guessed = shown & d.placed, shown & d.guessed
        pos_f = np.where(shown[:, None], pos, 0.0).astype(np.float32)
        scales = np.where(placed, JOINT_RADIUS_M * d.scale, 0.0)
        guess_scales = np.where(guessed, GUESS_SCALE * JOINT_RADIUS_M, 0.0)
        if d.selected is not None:
            scales[d.selected] *= SELECTED_SCALE
            guess_scales[d.selected] *= SELECTED_SCALE
        colours = self._colours(d)
        rings, ring_scales = self._rings(d, geo, shown, pos_f, scales)
        bones = self.skeleton.bones
        seg = np.where(shown[bones].all(axis=1)[:, None, None], pos_f[bones], 0.0)
        with self.lock, self.client.atomic():
            self.true_mm = np.asarray(d.joints_mm, dtype=np.float64).copy()
            self.drawn, self.radii = pos, scales
            if d.has_2d is not None and d.uv_px is not None:
                self.true_uv = np.where(np.asarray(d.has_2d)[:, None], d.uv_px, np.nan)
            if self.drag.joint is None:
                self.joints.batched_positions = pos_f
            self.joints.batched_scales = scales.astype(np.float32)
            self.joints.batched_colors = colours
            self.guesses.batched_positions = pos_f
            self.guesses.batched_scales = guess_scales.astype(np.float32)
            self.guesses.batched_colors = colours
            self.bones.points = seg.astype(np.float32)
            self.handles2d.batched_positions = rings
            self.handles2d.batched_scales = ring_scales
            self.handles2d.batched_colors = colours
            for k, label in enumerate(self.labels):
                if shown[k]:
                    label.position = tuple(float(x) for x in pos_f[k])
                label.visible = bool(shown[k] and d.labels)

    def _colours(self, d: Drawing) -> np.ndarray:
        """Chain colours; occluded joints greyed (not transparent: viser 1.1 reports no instance
        for clicks and drags on instances drawn with opacity < 1); the selected one highlighted."""
        colours = self.base_colours.copy()
        if d.occluded is not None:
            w = float(self.colours["occluded_mix"])
            occ = np.asarray(d.occluded, dtype=bool)
            colours[occ] = (w * colours[occ] + (1.0 - w) * OCCLUDED_GREY).astype(np.uint8)
        if d.selected is not None:
            colours[d.selected] = self.colours["selected"]
        return colours

    def _rings(
        self, d: Drawing, geo: FrameGeometry, shown: np.ndarray, pos_f: np.ndarray, scales
    ) -> tuple[np.ndarray, np.ndarray]:
        j = len(pos_f)
        if d.has_2d is None or d.uv_px is None:
            return np.zeros((j, 3), np.float32), np.zeros(j, np.float32)
        has2d = np.asarray(d.has_2d, dtype=bool)
        h2d = geo.pixel_to_scene(np.where(has2d[:, None], d.uv_px, 0.0), offset_mm=2.0)
        # footprint of each joint's sphere on the image plane (perspective from the sensor)
        depth_mm = np.where(shown, pos_f[:, 2] * 1000.0 + geo.centre_mm[2], geo.plane_z_mm)
        footprint = scales * geo.plane_z_mm / np.maximum(depth_mm, 1.0)
        radius = np.maximum(HANDLE2D_MIN_RADIUS_M, HANDLE2D_CLEARANCE * footprint)
        return h2d.astype(np.float32), np.where(has2d, radius, 0.0).astype(np.float32)

    def joint_hit(self, origin: np.ndarray, direction: np.ndarray) -> int | None:
        """The placed joint whose drawn sphere the ray hits first, or None."""
        pos, radius = self.drawn, self.radii
        ok = np.all(np.isfinite(pos), axis=1) & (radius > 0)
        if not ok.any():
            return None
        dirn = np.asarray(direction, dtype=np.float64)
        dirn = dirn / np.linalg.norm(dirn)
        rel = np.where(ok[:, None], pos, 0.0) - np.asarray(origin, dtype=np.float64)
        along = rel @ dirn
        perp = np.linalg.norm(rel - along[:, None] * dirn, axis=1)
        hit = ok & (along > 0) & (perp <= 1.05 * radius)
        if not hit.any():
            return None
        return int(np.flatnonzero(hit)[np.argmin(along[hit])])

    # ------------------------------------------------------------------ drags
    def _on_joint_drag(self, event: viser.SceneNodeDragEvent) -> None:
        k, panel, data = event.instance_index, self.panel, self.data
        if k is None or panel is None or data is None:
            return
        if event.phase == "start":
            self.drag.joint = None
            if panel.can_drag(int(k)) and np.all(np.isfinite(self.drawn[k])):
                true = data.geometry.to_scene(self.true_mm[k])
                grab = self.drawn[k] - np.asarray(event.start_position)
                self.drag.start(int(k), grab, true - self.drawn[k])
            return
        if not self.drag.active(k):
            return
        if event.phase == "update":
            with self.lock:
                positions = np.asarray(self.joints.batched_positions, dtype=np.float64).copy()
                positions[k] = self.drag.update(np.asarray(event.end_position))
                self.joints.batched_positions = positions.astype(np.float32)
            return
        k, scene_xyz = self.drag.end(np.asarray(event.end_position))
        xyz = data.geometry.from_scene(scene_xyz)
        if xyz[2] > 0:
            panel.on_drop(k, xyz)

    def _on_ring_drag(self, event: viser.SceneNodeDragEvent) -> None:
        """Drag a 2D ring within the image plane: it follows the pointer, the edit is on release.
        The drag point lies on a camera-aligned plane: the ray is cast from the browser camera,
        and the ring keeps the offset (px) from where its band was grabbed to its centre."""
        k, panel, data = event.instance_index, self.panel, self.data
        if k is None or panel is None or data is None or data.depth is None:
            return
        origin = np.asarray(self.client.camera.position, dtype=np.float64)
        geo = data.geometry
        if event.phase == "start":
            if not panel.can_drag(int(k)):
                return
            grab = geo.ray_to_pixel(origin, np.asarray(event.start_position) - origin)
            offset = self.true_uv[k] - grab if grab is not None else np.zeros(2)
            self.ring_drag.start(int(k), np.where(np.isfinite(offset), offset, 0.0))
            return
        uv = geo.ray_to_pixel(origin, np.asarray(event.end_position) - origin)
        if uv is None or not self.ring_drag.active(k):
            return
        if event.phase == "update":
            with self.lock:
                positions = np.asarray(self.handles2d.batched_positions, dtype=np.float64).copy()
                positions[k] = geo.pixel_to_scene(self.ring_drag.update(uv), offset_mm=2.0)
                self.handles2d.batched_positions = positions.astype(np.float32)
            return
        k, uv = self.ring_drag.end(uv)
        panel.on_ring_drop(k, uv)
