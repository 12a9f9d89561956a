"""The "Annotate" view: one object per connected browser, owning that client's scene nodes and panel.

Scene (client-scoped, under ``/annotate``, metres centred on the hand, see geometry.py):

* ``/annotate/cloud`` - the hand's point cloud coloured by depth (not clickable in viser: clicks
  are snapped server-side from ``scene.on_click`` rays);
* ``/annotate/image`` - the colour-mapped depth image on a plane behind the hand, lined up with
  the cloud; a click on it sets the selected joint's 2D position;
* ``/annotate/handles2d`` - the 2D annotations as flat rings on the image plane, wider than the
  joint spheres in front of them (draggable within the plane, grabbed by the visible band);
* ``/annotate/joints`` - the *placed* joints as ONE batched mesh (draggable in 3D), positions
  from the live lift (or the annotation until the first lift arrives); the selected joint
  highlighted;
* ``/annotate/guesses`` - the joints not placed yet where the live lift guesses them: small and
  faded, and with no click or drag binding, so a click "through" a guess reaches the image (or the
  cloud) behind it and places the selected joint;
* ``/annotate/bones`` - skeleton line segments; ``/annotate/labels/<k>`` - joint labels.

Clicks: in mode *2D on image* a click on the image, a 2D ring or a placed joint always sets the
selected joint's 2D position (the ray's pixel on the image plane); joints are selected with the
*Joint* list, the hotkeys, or by dragging. In mode *3D on cloud* a click on a placed joint's sphere
selects that joint and never moves it; any other click snaps the selected joint to the cloud, and
only the selected joint's sphere can be dragged.

Frame changes assign new arrays to these handles; nothing is recreated. Every edit goes through
:class:`~app.annotate_state.AnnotateState` (session commands); the view re-renders from the
session when the server forwards the journal entry (``on_entry``) and when the worker delivers a
lift (``on_lift``). Locking rule: the view lock guards handle assignment only; it is never held
while calling into the session (whose lock is held while entries are dispatched).
"""

from __future__ import annotations

import json
import threading
import time
import traceback
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import trimesh
import viser

from handanno_core.annotation import FrameAnnotation
from handanno_core.session import JournalEntry, SessionError

from .annotate_state import AnnotateState, edited_joints, entry_frame
from .frames import FrameData
from .geometry import pull_in_front_of_surface
from .hotkeys import bind_all
from .scene_nodes import UNIT_SPHERE, add_bones, add_hand_cloud, add_joint_meshes, show_hand_cloud
from .worker import LiftOutcome

if TYPE_CHECKING:
    from .server import AnnoServer

STATIC = Path(__file__).resolve().parent.parent / "static"
ROOT = "/annotate"
JOINT_RADIUS_M = 0.0045
#: 2D markers are flat rings on the image plane. From the sensor view (the default) each joint's
#: sphere sits right in front of its marker, so the ring is drawn CLEARANCE times wider than the
#: sphere's footprint on the plane: its outer band stays visible and grabbable. Inner radius is
#: RING_INNER of the outer one (the depth image shows through the hole).
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


def load_colours() -> dict[str, Any]:
    try:
        return json.loads((STATIC / "colours.json").read_text())
    except (OSError, ValueError):
        return {
            "root": [240, 240, 240],
            "chains": [
                [230, 60, 60],
                [240, 160, 40],
                [70, 190, 80],
                [60, 140, 230],
                [190, 80, 220],
            ],
            "selected": [255, 255, 0],
            "handle_2d": [255, 255, 255],
            "occluded_mix": 0.35,
        }


def joint_colours(parents: np.ndarray, colours: dict[str, Any]) -> np.ndarray:
    """(J, 3) uint8: the root in ``root`` colour, each subtree of the root in its chain colour."""
    parents = np.asarray(parents)
    out = np.zeros((len(parents), 3), np.uint8)
    chains = colours["chains"]
    root_children = [int(c) for c in np.flatnonzero(parents == np.flatnonzero(parents < 0)[0])]
    for j in range(len(parents)):
        k = j
        while parents[k] >= 0 and k not in root_children:
            k = int(parents[k])
        out[j] = colours["root"] if parents[j] < 0 else chains[root_children.index(k) % len(chains)]
    return out


def short_name(name: str) -> str:
    """'index_tip' -> 'I-tip'; used for labels."""
    if "_" not in name:
        return name
    finger, part = name.split("_", 1)
    return f"{finger[0].upper()}-{part}"


class AnnotateView:
    """Per-client annotation view; see the module docstring."""

    name = "Annotate"

    def __init__(self, app: AnnoServer, client: viser.ClientHandle):
        self.app = app
        self.client = client
        self.session = app.session
        self.state = AnnotateState(app.session, client=app.client_name(client))
        self.skeleton = app.session.skeleton
        self._lock = threading.RLock()
        self._told_hotkeys_paused = False
        self._handle2d_grab_px = np.zeros(2)  # grab point - marker centre of a 2D drag, px
        # Every redraw runs on this view's own single thread, in order: edits, lift results and
        # navigation from different threads never interleave half-drawn states, and the session's
        # listener (which holds the session lock) only enqueues.
        self._ui = ThreadPoolExecutor(1, thread_name_prefix=f"view-{client.client_id}")
        self._shown_frame = -1
        self._frame_data: FrameData | None = None
        self._annotation: FrameAnnotation = FrameAnnotation.empty(self.skeleton.num_joints)
        self._lifted: LiftOutcome | None = None
        #: (J, 3) mm pre-filled joints of the shown frame (AnnoServer.prefill), None if none
        self._prefill: np.ndarray | None = None
        #: joint -> journal seq of an edit the current lift result does not include yet.
        self._stale: dict[int, int] = {}
        self._drag_offset: np.ndarray | None = None
        self._drag_depth_offset = np.zeros(3)
        self._dragging: int | None = None
        #: (journal_seq, perf_counter) of the last lift assigned to the skeleton handle (latency).
        self.last_skeleton_update: tuple[int, float] | None = None
        #: (journal_seq, perf_counter) when an edit was first drawn (from the annotation, before lifting).
        self.last_edit_drawn: tuple[int, float] | None = None
        self.colours = load_colours()
        self.base_colours = joint_colours(self.skeleton.parent_array, self.colours)
        self._build_scene()
        self._build_gui()
        self.show_frame(self.state.frame, reset_camera=True)

    def _post(self, fn, *args: Any, **kwargs: Any) -> None:
        """Run ``fn`` on the view's UI thread (after everything posted before)."""

        def run() -> None:
            try:
                fn(*args, **kwargs)
            except Exception:
                traceback.print_exc()

        try:
            self._ui.submit(run)
        except RuntimeError:  # shut down: the client is gone
            pass

    def flush(self, timeout: float = 30.0) -> None:
        """Wait until every posted redraw has run (tests and benchmarks)."""
        self._ui.submit(lambda: None).result(timeout)

    # ================================================================== construction
    def _build_scene(self) -> None:
        scene = self.client.scene
        scene.set_up_direction("-y")  # OpenCV camera frame: y down
        cam = self.session.camera
        j = self.skeleton.num_joints
        self.cloud = add_hand_cloud(scene, f"{ROOT}/cloud")
        self.image = scene.add_image(
            f"{ROOT}/image",
            np.zeros((cam.height, cam.width, 3), np.uint8),
            render_width=0.3,
            render_height=0.2,
            format="jpeg",
            jpeg_quality=90,
            cast_shadow=False,
            receive_shadow=False,
        )
        ring = trimesh.creation.annulus(r_min=RING_INNER, r_max=1.0, height=0.05, sections=32)
        self.handles2d = add_joint_meshes(scene, f"{ROOT}/handles2d", ring, self.base_colours)
        self.joints = add_joint_meshes(scene, f"{ROOT}/joints", UNIT_SPHERE, self.base_colours)
        # no click/drag binding: viser raycasts only bound nodes, so guesses never catch a click
        self.guesses = add_joint_meshes(
            scene,
            f"{ROOT}/guesses",
            UNIT_SPHERE,
            self.base_colours,
            batched_opacities=np.full(j, GUESS_OPACITY, np.float32),
        )
        self.bones = add_bones(scene, f"{ROOT}/bones", self.skeleton.bones, self.base_colours)
        self.labels = [
            scene.add_label(
                f"{ROOT}/labels/{k}",
                short_name(self.skeleton.joint_names[k]),
                position=(0.0, 0.0, 0.0),
                visible=False,
                font_screen_scale=0.7,
                anchor="bottom-left",
            )
            for k in range(j)
        ]

        @self.image.on_click
        def _(event: viser.SceneNodePointerEvent) -> None:
            if event.modifier is None and self.state.click_mode == "2d":
                self.click_image(np.asarray(event.ray_origin), np.asarray(event.ray_direction))

        @scene.on_click()
        def _(event: viser.SceneClickEvent) -> None:
            if self.state.click_mode == "3d":
                self.click_scene_3d(np.asarray(event.ray_origin), np.asarray(event.ray_direction))

        @scene.on_click(modifier="shift")
        def _(event: viser.SceneClickEvent) -> None:
            self.click_scene_3d(np.asarray(event.ray_origin), np.asarray(event.ray_direction))

        @self.joints.on_click
        def _(event: viser.SceneNodePointerEvent) -> None:
            self.click_joint(
                event.instance_index,
                np.asarray(event.ray_origin),
                np.asarray(event.ray_direction),
                event.modifier,
            )

        @self.handles2d.on_click
        def _(event: viser.SceneNodePointerEvent) -> None:
            # a press on a ring that does not become a drag is a click on the image under it
            if event.modifier is None and self.state.click_mode == "2d":
                self.click_image(np.asarray(event.ray_origin), np.asarray(event.ray_direction))

        @self.joints.on_drag("left")
        async def _(event: viser.SceneNodeDragEvent) -> None:
            self._on_joint_drag(event)

        @self.handles2d.on_drag("left")
        async def _(event: viser.SceneNodeDragEvent) -> None:
            self._on_handle2d_drag(event)

    def _build_gui(self) -> None:
        gui = self.client.gui
        j = self.skeleton.num_joints
        self.frame_md = gui.add_markdown("")
        self.progress_md = gui.add_markdown("")
        self.progress_bar = gui.add_progress_bar(0.0)
        n = len(self.state.frames)
        self.frame_slider = gui.add_slider(
            "Reference",
            min=0,
            max=max(n - 1, 1),
            step=1,
            initial_value=self.state.index,
            disabled=n < 2,
        )
        self.nav = gui.add_button_group("Frame", ("◀ Prev (P)", "Next (N) ▶"))
        self.joint_dropdown = gui.add_dropdown(
            "Joint",
            tuple(self._joint_option(k) for k in range(j)),
            initial_value=self._joint_option(0),
        )
        self.visibility_button = gui.add_button(
            "Visibility: visible (V)", hint="Toggle visible / occluded"
        )
        self.depth_button = gui.add_button(
            "Depth vs parent: unknown (D)", hint="Cycle unknown → closer → farther"
        )
        self.click_mode = gui.add_dropdown(
            "Click places",
            ("2D on image", "3D on cloud"),
            initial_value="2D on image",
            hint="Shift+click always snaps to the cloud",
        )
        self.edit_buttons = gui.add_button_group("Edit", ("Undo", "Redo", "Clear joint"))
        self.accept_button = gui.add_button(
            "Accept guesses (G)",
            hint="Place every joint not placed yet where its guess is drawn (one undo step)",
        )
        self.camera_button = gui.add_button(
            "Sensor view", hint="Look from the depth camera (image and cloud line up)"
        )
        self.follow_sensor = gui.add_checkbox(
            "Sensor view on frame change",
            True,
            hint="Put the camera at the depth sensor whenever the frame changes",
        )
        self.saved_md = gui.add_markdown("*no edits yet in this browser*")
        self.lift_md = gui.add_markdown("")
        self.message_md = gui.add_markdown("")
        with gui.add_folder("Help", expand_by_default=False):
            gui.add_markdown(self.app.help_markdown)

        @self.frame_slider.on_update
        def _(event: Any) -> None:
            if event.client is not None and int(self.frame_slider.value) != self.state.index:
                self._claim_scene()
                self.go_to_index(int(self.frame_slider.value))

        @self.nav.on_click
        def _(event: Any) -> None:
            self._claim_scene()
            self.next_frame() if event.target.value.startswith("Next") else self.prev_frame()

        @self.joint_dropdown.on_update
        def _(event: Any) -> None:
            joint = int(self.joint_dropdown.value.split()[0])
            if event.client is not None and joint != self.state.joint:
                self._claim_scene()
                self.select_joint(joint)

        @self.visibility_button.on_click
        def _(_: Any) -> None:
            self._claim_scene()
            self.toggle_visibility()

        @self.depth_button.on_click
        def _(_: Any) -> None:
            self._claim_scene()
            self.cycle_depth_order()

        @self.click_mode.on_update
        def _(_event: Any) -> None:
            self.state.click_mode = "3d" if self.click_mode.value.startswith("3D") else "2d"

        @self.edit_buttons.on_click
        def _(event: Any) -> None:
            self._claim_scene()
            {"Undo": self.undo, "Redo": self.redo, "Clear joint": self.clear_joint}[
                event.target.value
            ]()

        @self.accept_button.on_click
        def _(_: Any) -> None:
            self._claim_scene()
            self.accept_guesses()

        @self.camera_button.on_click
        def _(_: Any) -> None:
            self._claim_scene()
            self.reset_camera()

        actions = {
            "next_frame": self.next_frame,
            "prev_frame": self.prev_frame,
            "next_joint": lambda: self.select_joint(self.state.joint + 1),
            "prev_joint": lambda: self.select_joint(self.state.joint - 1),
            "toggle_visibility": self.toggle_visibility,
            "cycle_depth_order": self.cycle_depth_order,
            "clear_joint": self.clear_joint,
            "accept_guesses": self.accept_guesses,
            "toggle_click_mode": self._toggle_click_mode,
            "undo": self.undo,
            "redo": self.redo,
        }
        bind_all(
            gui,
            {name: self._hotkey_action(action) for name, action in actions.items()},
        )

    def _joint_option(self, k: int) -> str:
        """'4 I-tip (index_tip)': the *Joint* list shows the 3D label's name next to the full one."""
        name = self.skeleton.joint_names[k]
        short = short_name(name)
        return f"{k} {short} ({name})" if short != name else f"{k} {name}"

    def _review_view(self) -> Any:
        return self.app.views.get(self.client.client_id, {}).get("Review")

    def _scene_shown(self) -> bool:
        """False while this browser shows the Review tab's scene (the annotate nodes hidden)."""
        return not getattr(self._review_view(), "scene_active", False)

    def _claim_scene(self) -> None:
        """Using the Annotate panel brings its scene back where the Review scene was shown."""
        review = self._review_view()
        if review is not None and review.scene_active:
            review.deactivate_scene()

    def _hotkey_action(self, action: Any) -> Any:
        """Hotkeys are page-wide in viser: while the Review scene is shown they would move or edit
        an annotate frame the user cannot see, so they do nothing then (and say so once); the
        frame keys N / P move the Review scene's frame instead."""
        review_actions = {
            self.next_frame: lambda: self._review_view().step_frame(+1),
            self.prev_frame: lambda: self._review_view().step_frame(-1),
        }

        def run(_client: Any) -> None:
            if self._scene_shown():
                action()
            elif action in review_actions:
                review_actions[action]()
            elif not self._told_hotkeys_paused:
                self._told_hotkeys_paused = True
                self.client.add_notification(
                    "Annotate hotkeys paused",
                    "The Review scene is shown. Use the Annotate panel, or 'Show annotate "
                    "scene' in the Review tab, to annotate again.",
                    auto_close_seconds=6.0,
                )

        return run

    # ================================================================== navigation
    @property
    def frame(self) -> int:
        return self.state.frame

    def go_to_index(self, index: int) -> None:
        self.state.go_to_index(index)
        self.show_frame(self.state.frame, reset_camera=bool(self.follow_sensor.value))

    def next_frame(self) -> None:
        self.go_to_index(self.state.index + 1)

    def prev_frame(self) -> None:
        self.go_to_index(self.state.index - 1)

    def select_joint(self, joint: int) -> None:
        self.state.select_joint(joint)
        self._post(self._render)

    def _toggle_click_mode(self) -> None:
        self.state.toggle_click_mode()
        self.click_mode.value = "3D on cloud" if self.state.click_mode == "3d" else "2D on image"

    def show_frame(self, frame: int, reset_camera: bool = False) -> None:
        """Load ``frame`` into the existing handles (on the view's UI thread)."""
        self._post(self._show_frame, frame, reset_camera)

    def _show_frame(self, frame: int, reset_camera: bool) -> None:
        if frame != self.state.frame:
            return  # navigation moved on before this ran
        data = self.app.frames.get(frame)
        annotation = self.session.annotation(frame) or FrameAnnotation.empty(
            self.skeleton.num_joints
        )
        lifted = self.app.worker.latest.get(frame)
        geo = data.geometry
        with self._lock, self.client.atomic():
            self._frame_data = data
            self._shown_frame = frame
            self._annotation = annotation
            self._lifted = lifted if lifted is not None and lifted.joints_mm is not None else None
            self._stale = {}
            self._prefill = None
            wrist = self._lifted.joints_mm if self._lifted is not None else None
            self.cloud.visible = show_hand_cloud(self.cloud, geo, wrist, self.skeleton)
            rw, rh = geo.image_render_size
            self.image.image = geo.image_rgb
            self.image.render_width = rw
            self.image.render_height = rh
            self.image.position = geo.image_position
            self.image.visible = data.depth is not None
        if reset_camera:
            self.reset_camera()
        if data.error:
            self.client.add_notification(
                "Frame problem", data.error, color="yellow", auto_close_seconds=8.0
            )
        if self._lifted is None and annotation.annotated.any():
            self.app.worker.submit(frame)
        if self._lifted is None and not annotation.annotated.all():
            threading.Thread(
                target=self._load_prefill, args=(frame,), name="handanno-prefill", daemon=True
            ).start()
        self._render()

    def _load_prefill(self, frame: int) -> None:
        """Pre-fill ``frame`` off the UI thread (it may run one propagation step), then draw it."""
        joints = self.app.prefill(frame)
        if joints is not None:
            self._post(self._apply_prefill, frame, joints)

    def _apply_prefill(self, frame: int, joints: np.ndarray) -> None:
        if frame == self._shown_frame:
            self._prefill = joints
            self._render()

    def reset_camera(self) -> None:
        """Put the browser camera at the depth sensor, looking at the hand (pixels line up); on
        large images (>= 512 px wide) the view frames the hand's crop, not the whole image."""
        data = self._frame_data
        if data is None:
            return
        geo = data.geometry
        cam = self.session.camera
        with self.client.atomic():
            self.client.camera.up_direction = (0.0, -1.0, 0.0)
            half = cam.height / 2.0 / cam.fy
            if cam.width >= 512 and geo.centre_mm[2] > 0:  # large image: frame the hand's crop
                cube = self.session.model.settings.cube_mm
                half = min(half, 0.65 * cube / float(geo.centre_mm[2]))
            self.client.camera.fov = float(2.0 * np.arctan(half))
            self.client.camera.position = geo.sensor_position
            self.client.camera.look_at = (0.0, 0.0, 0.0)

    # ================================================================== clicks and drags
    def click_image(self, origin: np.ndarray, direction: np.ndarray) -> JournalEntry | None:
        """A click ray on the image plane -> the selected joint's 2D position."""
        data = self._frame_data
        if data is None or data.depth is None:
            return None
        uv = data.geometry.ray_to_pixel(origin, direction)
        if uv is None:
            return None
        return self._edit(lambda: self.state.place_2d(uv))

    def click_cloud(self, origin: np.ndarray, direction: np.ndarray) -> JournalEntry | None:
        """A click ray -> snap to the nearest cloud point along it -> the selected joint in 3D."""
        data = self._frame_data
        if data is None:
            return None
        xyz = data.geometry.nearest_cloud_point(origin, direction)
        if xyz is None:
            return None
        return self._edit(lambda: self.state.place_3d(xyz))

    def click_joint(
        self, k: int | None, origin: np.ndarray, direction: np.ndarray, modifier: str | None
    ) -> JournalEntry | None:
        """A click on a placed joint's sphere. Mode 2D (no modifier): the click places the
        selected joint's 2D position under the pointer, like a click on the image behind the
        sphere (so neighbouring joints never swallow clicks). Mode 3D or Shift: selects joint
        ``k`` and never moves it."""
        if modifier is None and self.state.click_mode == "2d":
            return self.click_image(origin, direction)
        if k is None:
            k = self._placed_joint_hit(origin, direction)
        if k is not None:
            self.select_joint(int(k))
        return None

    def click_scene_3d(self, origin: np.ndarray, direction: np.ndarray) -> JournalEntry | None:
        """A click in mode 3D (or a Shift+click): on a placed joint's sphere it selects that joint
        (the sphere's own click event may arrive before or after this one); anywhere else, guesses
        included, it snaps the selected joint to the cloud."""
        k = self._placed_joint_hit(origin, direction)
        if k is not None:
            self.select_joint(k)
            return None
        return self.click_cloud(origin, direction)

    def _placed_joint_hit(self, origin: np.ndarray, direction: np.ndarray) -> int | None:
        """The placed joint whose drawn sphere the ray hits first, or None."""
        pos = self._joint_positions_scene()
        radius = self._placed_radii()
        ok = np.all(np.isfinite(pos), axis=1) & (radius > 0)
        if not ok.any():
            return None
        d = np.asarray(direction, dtype=np.float64)
        d = d / np.linalg.norm(d)
        rel = np.where(ok[:, None], pos, 0.0) - np.asarray(origin, dtype=np.float64)
        along = rel @ d
        perp = np.linalg.norm(rel - along[:, None] * d, axis=1)
        hit = ok & (along > 0) & (perp <= 1.05 * radius)
        if not hit.any():
            return None
        return int(np.flatnonzero(hit)[np.argmin(along[hit])])

    def _placed_radii(self) -> np.ndarray:
        """(J,) drawn sphere radius (scene m) of each placed joint, 0 for joints not placed."""
        radius = np.where(self._annotation.annotated, JOINT_RADIUS_M, 0.0)
        radius[self.state.joint] *= SELECTED_SCALE
        return radius

    def _on_joint_drag(self, event: viser.SceneNodeDragEvent) -> None:
        k = event.instance_index
        if k is None or self._frame_data is None:
            return
        if event.phase == "start" and self.state.click_mode == "3d" and k != self.state.joint:
            # 3D mode: only the selected joint moves; grabbing another one selects it
            self._dragging = None
            self._drag_offset = None
            self.select_joint(int(k))
            return
        if event.phase == "start":
            geo = self._frame_data.geometry
            true_mm = self._joint_positions_mm()
            drawn = geo.to_scene(self._display_mm(true_mm))
            if not np.all(np.isfinite(drawn[k])):
                return
            self._dragging = int(k)
            # new joint = drop point + (drawn - grab point) + (true - drawn)
            self._drag_offset = drawn[k] - np.asarray(event.start_position)
            self._drag_depth_offset = geo.to_scene(true_mm[k]) - drawn[k]
            self.state.select_joint(k)
            return
        if self._dragging != k or self._drag_offset is None:
            return
        new = np.asarray(event.end_position) + self._drag_offset
        if event.phase == "update":
            with self._lock:
                positions = np.asarray(self.joints.batched_positions, dtype=np.float64).copy()
                positions[k] = new
                self.joints.batched_positions = positions.astype(np.float32)
            return
        # end
        self._dragging = None
        self._drag_offset = None
        xyz = self._frame_data.geometry.from_scene(new + self._drag_depth_offset)
        if xyz[2] > 0:
            self._edit(lambda: self.state.place_3d(xyz, joint=k, advance=False))

    def _on_handle2d_drag(self, event: viser.SceneNodeDragEvent) -> None:
        """Drag a 2D marker within the image plane: it follows the pointer, the edit is on release."""
        k = event.instance_index
        data = self._frame_data
        if k is None or data is None or data.depth is None:
            return
        # The drag point lies on a camera-aligned plane: cast the ray from the browser camera.
        origin = np.asarray(self.client.camera.position, dtype=np.float64)
        if event.phase == "start":
            self.state.select_joint(k)
            # the ring is grabbed by its band, off its centre: keep that offset while dragging
            grab = data.geometry.ray_to_pixel(origin, np.asarray(event.start_position) - origin)
            ann = self._annotation
            self._handle2d_grab_px = (
                grab - ann.uv_px[k] if grab is not None and ann.has_2d[k] else np.zeros(2)
            )
            return
        uv = data.geometry.ray_to_pixel(origin, np.asarray(event.end_position) - origin)
        if uv is None:
            return
        uv = uv - self._handle2d_grab_px
        if event.phase == "update":
            with self._lock:
                positions = np.asarray(self.handles2d.batched_positions, dtype=np.float64).copy()
                positions[k] = data.geometry.pixel_to_scene(uv, offset_mm=2.0)
                self.handles2d.batched_positions = positions.astype(np.float32)
            return
        self._edit(lambda: self.state.place_2d(uv, joint=k, advance=False))

    # ================================================================== edits
    def toggle_visibility(self) -> JournalEntry | None:
        return self._edit(self.state.toggle_visibility)

    def cycle_depth_order(self) -> JournalEntry | None:
        return self._edit(self.state.cycle_depth_order)

    def clear_joint(self) -> JournalEntry | None:
        return self._edit(self.state.clear_joint)

    def accept_guesses(self) -> JournalEntry | None:
        """Every joint not placed yet goes where its guess is drawn (one journaled Batch)."""
        if self._frame_data is None:
            return None
        entry = self._edit(lambda: self.state.accept_guesses(self._joint_positions_mm()))
        if entry is None:
            self.client.add_notification("No guesses to accept", "", auto_close_seconds=2.0)
        return entry

    def undo(self) -> JournalEntry | None:
        entry = self._edit(self.state.undo)
        if entry is None:
            self.client.add_notification("Nothing to undo", "", auto_close_seconds=2.0)
        else:
            self._follow(entry)
        return entry

    def redo(self) -> JournalEntry | None:
        entry = self._edit(self.state.redo)
        if entry is None:
            self.client.add_notification("Nothing to redo", "", auto_close_seconds=2.0)
        else:
            self._follow(entry)
        return entry

    def _follow(self, entry: JournalEntry) -> None:
        """Undo/redo of an edit on another frame: go there so the change is visible."""
        frame = entry_frame(entry)
        if frame != self.frame and frame in self.state.frames:
            self.go_to_index(self.state.frames.index(frame))

    def _edit(self, action) -> JournalEntry | None:
        """Run one edit; show "saved" only once the session acknowledged it (journal fsynced)."""
        try:
            entry = action()
        except SessionError as exc:
            self.saved_md.content = f"**⚠ NOT saved:** {exc}"
            self.client.add_notification(
                "Edit NOT saved", str(exc), color="red", with_close_button=True
            )
            return None
        except ValueError as exc:
            self.client.add_notification(
                "Edit refused", str(exc), color="yellow", auto_close_seconds=5.0
            )
            return None
        if entry is not None:
            stamp = time.strftime("%H:%M:%S", time.localtime(entry.time))
            what = {"do": "edit", "undo": "undo", "redo": "redo"}[entry.action]
            self.saved_md.content = f"✓ saved {stamp} ({what} #{entry.seq})"
        self._post(self._render)
        return entry

    # ================================================================== session / worker events
    def on_entry(self, entry: JournalEntry, frame: int) -> None:
        """A journal entry on ``frame`` was acknowledged (any client; called under the session lock)."""
        self._post(self._apply_entry, entry, frame)

    def _apply_entry(self, entry: JournalEntry, frame: int) -> None:
        if frame != self._shown_frame:
            if entry.client != self.state.client:
                self._update_panel()  # progress may have changed
            return
        self._annotation = self.session.annotation(frame) or FrameAnnotation.empty(
            self.skeleton.num_joints
        )
        for joint in edited_joints(entry, self.skeleton.num_joints):
            self._stale[joint] = entry.seq
        if entry.client != self.state.client:
            self.client.add_notification(
                "Frame edited elsewhere",
                f"another annotator changed frame {frame}",  # never another client's id (issue 16)
                color="blue",
                auto_close_seconds=4.0,
            )
        self._render(edit_seq=entry.seq)

    def on_lift(self, outcome: LiftOutcome) -> None:
        """The worker lifted ``outcome.frame`` (called on the worker thread)."""
        self._post(self._apply_lift, outcome)

    def _apply_lift(self, outcome: LiftOutcome) -> None:
        if outcome.frame != self._shown_frame:
            return
        if outcome.joints_mm is None:
            self.lift_md.content = f"*skeleton: {outcome.error}*"
            if not self._annotation.annotated.any():
                # everything undone or cleared: no skeleton is left to draw (or to click)
                self._lifted = None
                self._stale = {}
                self._render()
            return
        self._lifted = outcome
        self._stale = {j: seq for j, seq in self._stale.items() if seq > outcome.journal_seq}
        self._render(lift=outcome)

    # ================================================================== drawing
    def _joint_positions_mm(self) -> np.ndarray:
        """(J, 3) mm: lifted joints (else the pre-fill for joints not placed), else placed 3D,
        else 2D on the depth surface; NaN = unknown."""
        ann = self._annotation
        data = self._frame_data
        out = np.full((self.skeleton.num_joints, 3), np.nan)
        if self._lifted is not None and self._lifted.joints_mm is not None:
            out[:] = self._lifted.joints_mm
            # Joints edited after that lift follow the annotation at once (instant feedback);
            # the next lift result moves the whole skeleton.
            stale = [j for j in self._stale if ann.annotated[j]]
            out[stale] = np.nan
        elif self._prefill is not None:  # before the first lift: the pre-filled pose
            out[:] = self._prefill
            out[ann.annotated] = np.nan  # placed joints are drawn where they were placed
        if data is None:
            return out
        missing = ~np.all(np.isfinite(out), axis=1)
        if missing.any():
            out[missing & ann.has_3d] = ann.xyz_mm[missing & ann.has_3d]
            only2d = missing & ~ann.has_3d & ann.has_2d
            if only2d.any():
                uv = ann.uv_px[only2d]
                z = np.full(len(uv), data.geometry.centre_mm[2])
                if data.depth is not None:
                    cam = self.session.camera
                    col = np.clip(np.round(uv[:, 0]).astype(int), 0, cam.width - 1)
                    row = np.clip(np.round(uv[:, 1]).astype(int), 0, cam.height - 1)
                    d = data.depth[row, col]
                    z = np.where(d > 0, d, z)
                out[only2d] = self.session.camera.backproject(uv, z)
        return out

    def _joint_positions_scene(self) -> np.ndarray:
        """(J, 3) scene positions where the joint handles are *drawn* (see _display_mm)."""
        if self._frame_data is None:
            return np.full((self.skeleton.num_joints, 3), np.nan)
        return self._frame_data.geometry.to_scene(self._display_mm(self._joint_positions_mm()))

    def _display_mm(self, joints_mm: np.ndarray) -> np.ndarray:
        """Joint centres lie behind the observed surface (lifting puts them ~10 mm inside the
        finger), so the cloud would hide them. Draw each joint that is behind the surface at
        its pixel pulled along its camera ray to ``SURFACE_MARGIN_MM`` in front of the surface:
        from the sensor it is exactly where it projects, and it is never buried in the cloud.
        Drags keep the offset (new joint = drop point + (true - drawn))."""
        data = self._frame_data
        depth = None if data is None else data.depth
        return pull_in_front_of_surface(joints_mm, depth, self.session.camera)

    def _render(self, lift: LiftOutcome | None = None, edit_seq: int | None = None) -> None:
        """Assign the joints, bones, labels, 2D handles and panel from the current state."""
        data = self._frame_data
        if data is None:
            return
        geo = data.geometry
        ann = self._annotation
        sel = self.state.joint
        pos = self._joint_positions_scene()
        shown = np.all(np.isfinite(pos), axis=1)
        placed = shown & ann.annotated
        guessed = shown & ~ann.annotated
        pos_f = np.where(shown[:, None], pos, 0.0).astype(np.float32)
        scales = np.where(placed, JOINT_RADIUS_M, 0.0)
        scales[sel] *= SELECTED_SCALE
        guess_scales = np.where(guessed, GUESS_SCALE * JOINT_RADIUS_M, 0.0)
        guess_scales[sel] *= SELECTED_SCALE
        colours = self.base_colours.copy()
        # occluded joints are greyed, not transparent: viser 1.1 reports no instance (and no
        # position) for clicks and drags on instances drawn with opacity < 1
        w = float(self.colours["occluded_mix"])
        occluded = ~ann.visible
        colours[occluded] = (w * colours[occluded] + (1.0 - w) * OCCLUDED_GREY).astype(np.uint8)
        colours[sel] = self.colours["selected"]
        has2d = ann.has_2d
        h2d = geo.pixel_to_scene(np.where(has2d[:, None], ann.uv_px, 0.0), offset_mm=2.0)
        # footprint of each joint's sphere on the image plane (perspective from the sensor)
        depth_mm = np.where(shown, pos_f[:, 2] * 1000.0 + geo.centre_mm[2], geo.plane_z_mm)
        footprint = scales * geo.plane_z_mm / np.maximum(depth_mm, 1.0)
        h2d_scales = np.where(
            has2d, np.maximum(HANDLE2D_MIN_RADIUS_M, HANDLE2D_CLEARANCE * footprint), 0.0
        )
        bones = self.skeleton.bones
        seg = pos_f[bones]  # (B, 2, 3)
        seg_ok = shown[bones].all(axis=1)
        seg = np.where(seg_ok[:, None, None], seg, 0.0)
        with self._lock, self.client.atomic():
            if self._dragging is None:
                self.joints.batched_positions = pos_f
            self.joints.batched_scales = scales.astype(np.float32)
            self.joints.batched_colors = colours
            self.guesses.batched_positions = pos_f
            self.guesses.batched_scales = guess_scales.astype(np.float32)
            self.guesses.batched_colors = colours
            self.bones.points = seg.astype(np.float32)
            self.handles2d.batched_positions = h2d.astype(np.float32)
            self.handles2d.batched_scales = h2d_scales.astype(np.float32)
            self.handles2d.batched_colors = colours
            for k, label in enumerate(self.labels):
                if shown[k]:
                    label.position = tuple(float(x) for x in pos_f[k])
                label.visible = bool(shown[k])
            if edit_seq is not None:
                self.last_edit_drawn = (edit_seq, time.perf_counter())
            if lift is not None:
                self.last_skeleton_update = (lift.journal_seq, time.perf_counter())
                self.lift_md.content = f"*skeleton lifted in {1000 * lift.duration_s:.0f} ms*"
        if lift is not None:
            self.app.notify_skeleton_update(self, lift)
        self._update_panel()

    def _update_panel(self) -> None:
        st = self.state
        vis, order = st.joint_text()
        done, total = self.session.progress()
        data = self._frame_data
        complete = self.session.is_annotated(st.frame)
        progress_text = st.progress_text()
        with self._lock:
            where = (
                f"reference {st.index + 1} of {len(st.frames)}"
                if st.has_selection
                else f"frame {st.index + 1} of {len(st.frames)}"
            )
            status = "✓ complete" if complete else "in progress"
            self.frame_md.content = f"**Frame {st.frame}** ({where}), {status}"
            self.progress_md.content = progress_text
            self.progress_bar.value = 100.0 * done / total if total else 0.0
            if int(self.frame_slider.value) != st.index:
                self.frame_slider.value = st.index
            label = self._joint_option(st.joint)
            if self.joint_dropdown.value != label:
                self.joint_dropdown.value = label
            self.visibility_button.label = f"Visibility: {vis} (V)"
            self.depth_button.label = f"Depth vs parent: {order} (D)"
            self.message_md.content = (
                f"**⚠ {data.error}**" if data is not None and data.error else ""
            )
            if not self.app.worker.available:
                self.lift_md.content = "*live lifting unavailable (handanno_core.lift missing)*"

    def close(self) -> None:
        """The client disconnected: nothing to persist (edits are journaled as they happen)."""
        self._ui.shutdown(wait=False, cancel_futures=True)
