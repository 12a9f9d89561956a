"""The Annotate tab: its widgets, their callbacks, and how it draws the shared hand scene.

Clicks: in mode *2D on image* a click on the image, a 2D ring or a placed joint always sets the
selected joint's 2D position (the ray's pixel on the image plane); joints are selected with the
*Joint* list, the hotkeys, or by dragging. In mode *3D on cloud* a click on a placed joint's sphere
selects that joint and never moves it; any other click snaps the selected joint to the cloud, and
only the selected joint's sphere can be dragged. Guessed joints (drawn small and faded) never
catch a click.

Every edit goes through :class:`~app.control.annotate.AnnotateState` (session commands); the panel
re-renders when the event bus reports the journal entry or a lift (``on_update``, on the
client's UI thread).
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from handanno_core.annotation import FrameAnnotation
from handanno_core.session import JournalEntry, SessionError
from handanno_core.synth import template_hand

from ..control.annotate import display_joints
from ..control.events import Update, UpdateTopic, entry_frame
from ..control.frames import FrameData
from ..control.jobs import LiftOutcome
from .hand_scene import Drawing
from .theme import hand_diagram_svg, joint_legend, joint_option

if TYPE_CHECKING:
    from .client_ui import ClientUI


@dataclass
class AnnotateWidgets:
    frame_md: Any
    progress_md: Any
    progress_bar: Any
    frame_slider: Any
    nav: Any
    joint_dropdown: Any
    visibility_button: Any
    depth_button: Any
    outside_button: Any
    click_mode: Any
    edit_buttons: Any
    accept_button: Any
    camera_button: Any
    follow_sensor: Any
    saved_md: Any
    lift_md: Any
    message_md: Any
    legend_md: Any


def make_annotate_widgets(
    gui: Any, options: tuple[str, ...], frames: int, index: int, help_md: str
):
    w = AnnotateWidgets(
        frame_md=gui.add_markdown(""),
        progress_md=gui.add_markdown(""),
        progress_bar=gui.add_progress_bar(0.0),
        frame_slider=gui.add_slider(
            "Reference",
            min=0,
            max=max(frames - 1, 1),
            step=1,
            initial_value=index,
            disabled=frames < 2,
        ),  # fmt: skip
        nav=gui.add_button_group("Frame", ("◀ Prev (P)", "Next (N) ▶")),
        joint_dropdown=gui.add_dropdown("Joint", options, initial_value=options[0]),
        visibility_button=gui.add_button(
            "Visibility: visible (V)", hint="Toggle visible / occluded"
        ),
        depth_button=gui.add_button(
            "Depth vs parent: unknown (D)", hint="Cycle unknown → closer → farther"
        ),
        outside_button=gui.add_button(
            "Outside the image (O)",
            hint="The selected joint lies past the image's border, where nobody can click it "
            "(press again to take the mark away)",
        ),
        click_mode=gui.add_dropdown(
            "Click places",
            ("2D on image", "3D on cloud"),
            initial_value="2D on image",
            hint="Shift+click always snaps to the cloud",
        ),  # fmt: skip
        edit_buttons=gui.add_button_group("Edit", ("Undo", "Redo", "Clear joint")),
        accept_button=gui.add_button(
            "Accept guesses (G)",
            hint="Place every joint not placed yet where its guess is drawn (one undo step)",
        ),
        camera_button=gui.add_button(
            "Sensor view", hint="Look from the depth camera (image and cloud line up)"
        ),
        follow_sensor=gui.add_checkbox(
            "Sensor view on frame change",
            True,
            hint="Put the camera at the depth sensor whenever the frame changes",
        ),  # fmt: skip
        saved_md=gui.add_markdown("*no edits yet in this browser*"),
        lift_md=gui.add_markdown(""),
        message_md=gui.add_markdown(""),
        legend_md=None,
    )
    with gui.add_folder("Joints (legend)", expand_by_default=False):
        w.legend_md = gui.add_html("")
    with gui.add_folder("Help", expand_by_default=False):
        gui.add_markdown(help_md)
    return w


def _bind_widgets(self: AnnotatePanel) -> None:
    """The panel's widget callbacks (using a widget shows the Annotate scene)."""
    w = self.w

    def claimed(fn):  # using the panel shows its scene
        def run(*args: Any) -> None:
            self.ui.show("annotate")
            fn(*args)

        return run

    w.frame_slider.on_update(
        lambda e: (
            e.client is not None
            and int(w.frame_slider.value) != self.state.index
            and claimed(self.go_to_index)(int(w.frame_slider.value))
        )
    )
    w.nav.on_click(
        claimed(lambda e: self.next_frame() if e.target.value.startswith("Next") else self.prev_frame())
    )  # fmt: skip
    w.joint_dropdown.on_update(
        lambda e: (
            e.client is not None
            and int(w.joint_dropdown.value.split()[0]) != self.state.joint
            and claimed(self.select_joint)(int(w.joint_dropdown.value.split()[0]))
        )
    )
    w.visibility_button.on_click(claimed(lambda _: self.toggle_visibility()))
    w.depth_button.on_click(claimed(lambda _: self.cycle_depth_order()))
    w.outside_button.on_click(claimed(lambda _: self.toggle_outside()))
    w.click_mode.on_update(lambda _: self._set_click_mode(w.click_mode.value))
    w.edit_buttons.on_click(
        claimed(lambda e: {"Undo": self.undo, "Redo": self.redo, "Clear joint": self.clear_joint}[e.target.value]())
    )  # fmt: skip
    w.accept_button.on_click(claimed(lambda _: self.accept_guesses()))
    w.camera_button.on_click(claimed(lambda _: self.ui.post(self.hand.reset_camera)))


class AnnotatePanel:
    """The Annotate tab of one browser; see the module docstring."""

    def __init__(self, ui: ClientUI, help_md: str):
        self.ui = ui
        self.ctx = ui.ctx
        self.client = ui.client
        self.session = ui.ctx.session
        self.skeleton = self.session.skeleton
        self.hand = ui.scene
        self.state = ui.ctx.annotate_state(ui.name)
        names = list(self.skeleton.joint_names)
        self._options = tuple(joint_option(names, k) for k in range(len(names)))
        self.w = make_annotate_widgets(
            self.client.gui, self._options, len(self.state.frames), self.state.index, help_md
        )
        self._shown_frame = -1
        self.frame_data: FrameData | None = None
        self._annotation = FrameAnnotation.empty(self.skeleton.num_joints)
        self._lifted: LiftOutcome | None = None
        #: (J, 3) mm pre-filled joints of the shown frame (AppContext.prefill), None if none
        self._prefill: np.ndarray | None = None
        #: joint -> journal seq of an edit the current lift result does not include yet
        self._stale: dict[int, int] = {}
        #: (journal_seq, perf_counter) of the last lift drawn / when an edit was first drawn
        self.last_skeleton_update: tuple[int, float] | None = None
        self.last_edit_drawn: tuple[int, float] | None = None
        self.clicks = AnnotateClicks(self)
        hand = template_hand(self.skeleton, np.zeros(3))  # the legend's hand diagram
        self._diagram_xy = None if hand is None else hand[:, :2]
        if self.session.can_undo(ui.name):
            self.w.saved_md.content = "✓ every edit of this browser is saved (undo available)"
        _bind_widgets(self)

    @property
    def frame(self) -> int:
        return self.state.frame

    @property
    def active(self) -> bool:
        return self.ui.state.active_scene == "annotate"

    def flush(self, timeout: float = 30.0) -> None:
        self.ui.flush(timeout)

    def _set_click_mode(self, value: str) -> None:
        self.state.click_mode = "3d" if value.startswith("3D") else "2d"

    # ================================================================== navigation
    def activate(self, reset_camera: bool = False) -> None:
        """This panel's scene is shown: draw it (on the UI thread)."""
        self._show_frame(self.state.frame, reset_camera)

    def deactivated(self) -> None:
        pass

    def go_to_index(self, index: int) -> None:
        self.state.go_to_index(index)
        self.show_frame(self.state.frame, reset_camera=bool(self.w.follow_sensor.value))

    def next_frame(self) -> None:
        self.go_to_index(self.state.index + 1)

    def prev_frame(self) -> None:
        self.go_to_index(self.state.index - 1)

    def select_joint(self, joint: int) -> None:
        self.state.select_joint(joint)
        self.ui.post(self._render)

    def toggle_click_mode(self) -> None:
        self.state.toggle_click_mode()
        self.w.click_mode.value = "3D on cloud" if self.state.click_mode == "3d" else "2D on image"

    def show_frame(self, frame: int, reset_camera: bool = False) -> None:
        self.ui.post(self._show_frame, frame, reset_camera)

    def _show_frame(self, frame: int, reset_camera: bool) -> None:
        if frame != self.state.frame or not self.active:
            return  # navigation moved on before this ran, or the Review scene is shown
        data = self.ctx.frames.get(frame)
        annotation = self.session.annotation(frame) or FrameAnnotation.empty(
            self.skeleton.num_joints
        )
        lifted = self.ctx.worker.latest.get(frame)
        self.frame_data, self._shown_frame, self._annotation = data, frame, annotation
        self._lifted = lifted if lifted is not None and lifted.joints_mm is not None else None
        self._stale, self._prefill = {}, None
        self.w.lift_md.content = ""  # the previous frame's lift says nothing about this one
        wrist = self._lifted.joints_mm if self._lifted is not None else None
        self.hand.show_frame(data, wrist, image=True)
        if reset_camera:
            self.hand.reset_camera()
        if data.error:
            self.client.add_notification(
                "Frame problem", data.error, color="yellow", auto_close_seconds=8.0
            )
        if self._lifted is None and annotation.annotated.any():
            self.ctx.worker.submit(frame)
        if self._lifted is None and not annotation.complete.all():
            threading.Thread(
                target=self._load_prefill, args=(frame,), name="handanno-prefill", daemon=True
            ).start()
        self._render()

    def _load_prefill(self, frame: int) -> None:
        """Pre-fill ``frame`` off the UI thread (it may run one propagation step), then draw it."""
        joints = self.ctx.prefill(frame)
        if joints is not None:
            self.ui.post(self._apply_prefill, frame, joints)

    def _apply_prefill(self, frame: int, joints: np.ndarray) -> None:
        if frame == self._shown_frame and self.active:
            self._prefill = joints
            self._render()

    # ================================================================== edits
    def toggle_visibility(self) -> JournalEntry | None:
        return self.edit(self.state.toggle_visibility)

    def cycle_depth_order(self) -> JournalEntry | None:
        return self.edit(self.state.cycle_depth_order)

    def toggle_outside(self) -> JournalEntry | None:
        return self.edit(self.state.toggle_outside)

    def clear_joint(self) -> JournalEntry | None:
        return self.edit(self.state.clear_joint)

    def accept_guesses(self) -> JournalEntry | None:
        """Every joint not placed yet goes where its guess is drawn (one journaled Batch)."""
        if self.frame_data is None:
            return None
        entry = self.edit(lambda: self.state.accept_guesses(self.joint_positions_mm()))
        if entry is None:
            self.client.add_notification("No guesses to accept", "", auto_close_seconds=2.0)
        return entry

    def undo(self) -> JournalEntry | None:
        return self._undo_redo(self.state.undo, "undo")

    def redo(self) -> JournalEntry | None:
        return self._undo_redo(self.state.redo, "redo")

    def _undo_redo(self, action, what: str) -> JournalEntry | None:
        entry = self.edit(action)
        if entry is None:
            self.client.add_notification(f"Nothing to {what}", "", auto_close_seconds=2.0)
            return None
        frame = entry_frame(entry)  # an edit on another frame: go there so it is visible
        if frame != self.frame and frame in self.state.frames:
            self.go_to_index(self.state.frames.index(frame))
        return entry

    def edit(self, action) -> JournalEntry | None:
        """Run one edit; show "saved" only once the session acknowledged it (journal fsynced)."""
        self.ui.show("annotate")
        try:
            entry = action()
        except SessionError as exc:
            self.w.saved_md.content = f"**⚠ NOT saved:** {exc}"
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
            self.w.saved_md.content = f"✓ saved {stamp} ({what} #{entry.seq})"
        self.ui.post(self._render)
        return entry

    # ================================================================== updates
    def on_update(self, update: Update) -> None:
        """An :class:`Update` from the bus (on the UI thread)."""
        if not self.active:
            return
        if UpdateTopic.ANNOTATION in update.topics:
            self._apply_edit(update)
        elif UpdateTopic.LIFT in update.topics and update.frame == self._shown_frame:
            self._apply_lift(update.lift)
        elif UpdateTopic.JOB in update.topics or UpdateTopic.REFERENCES in update.topics:
            self._update_panel()

    def _apply_edit(self, update: Update) -> None:
        if update.frame != self._shown_frame:
            if update.client != self.state.client:
                self._update_panel()  # progress may have changed
            return
        self._annotation = self.session.annotation(update.frame) or FrameAnnotation.empty(
            self.skeleton.num_joints
        )
        for joint in update.joints:
            self._stale[joint] = update.seq
        if update.client != self.state.client:
            self.client.add_notification(
                "Frame edited elsewhere",
                f"another annotator changed frame {update.frame}",  # never another client's id
                color="blue",
                auto_close_seconds=4.0,
            )
        self._render(edit_seq=update.seq)

    def _apply_lift(self, outcome: LiftOutcome) -> None:
        if outcome.joints_mm is None:
            self.w.lift_md.content = f"*frame {outcome.frame}: no skeleton: {outcome.error}*"
            if not self._annotation.annotated.any():
                # everything undone or cleared: no skeleton is left to draw (or to click)
                self._lifted, self._stale = None, {}
                self._render()
            return
        self._lifted = outcome
        self._stale = {j: seq for j, seq in self._stale.items() if seq > outcome.journal_seq}
        if self.frame_data is not None and outcome.frame == self._shown_frame:
            # the forearm is cut at the wrist plane as soon as a lift places the wrist
            self.hand.show_cloud(self.frame_data, outcome.joints_mm)
        self._render(lift=outcome)

    # ================================================================== drawing
    def joint_positions_mm(self) -> np.ndarray:
        """(J, 3) mm where each joint is drawn (:func:`~app.control.annotate.display_joints`)."""
        data = self.frame_data
        if data is None:
            return np.full((self.skeleton.num_joints, 3), np.nan)
        lifted = self._lifted.joints_mm if self._lifted is not None else None
        return display_joints(
            self._annotation, self.session.camera, data.depth, data.geometry.centre_mm,
            lifted_mm=lifted, stale=list(self._stale), prefill_mm=self._prefill,
        )  # fmt: skip

    def joint_positions_scene(self) -> np.ndarray:
        """(J, 3) scene positions where the joint handles are drawn."""
        return self.hand.to_scene(self.joint_positions_mm())

    def _render(self, lift: LiftOutcome | None = None, edit_seq: int | None = None) -> None:
        if self.frame_data is None or not self.active:
            return
        ann = self._annotation
        self.hand.draw(
            Drawing(
                self.joint_positions_mm(), placed=ann.annotated, guessed=~ann.annotated,
                selected=self.state.joint, occluded=~ann.visible, uv_px=ann.uv_px,
                has_2d=ann.has_2d,
            )
        )  # fmt: skip
        if edit_seq is not None:
            self.last_edit_drawn = (edit_seq, time.perf_counter())
        if lift is not None:
            self.last_skeleton_update = (lift.journal_seq, time.perf_counter())
            self.w.lift_md.content = (
                f"*frame {lift.frame}: skeleton lifted in {1000 * lift.duration_s:.0f} ms*"
            )
        self._update_panel()

    def _update_panel(self) -> None:
        st, w = self.state, self.w
        vis, order = st.joint_text()
        done, total = self.session.progress()
        where = f"{'reference' if st.has_selection else 'frame'} {st.index + 1} of {len(st.frames)}"
        status = "✓ complete" if self.session.is_annotated(st.frame) else "in progress"
        source = self.ctx.frames.source_name(st.frame)
        w.frame_md.content = f"**Frame {st.frame}** ({where}), {status}" + (
            f"  \n`{source}`" if source else ""
        )
        job = self.ctx.runner.status
        w.progress_md.content = st.progress_text() + (
            f"  \n*background: {job.text()}*" if job.running else ""
        )
        w.progress_bar.value = 100.0 * done / total if total else 0.0
        if int(w.frame_slider.value) != st.index:
            w.frame_slider.value = st.index
        if w.joint_dropdown.value != self._options[st.joint]:
            w.joint_dropdown.value = self._options[st.joint]
        w.visibility_button.label = f"Visibility: {vis} (V)"
        w.depth_button.label = f"Depth vs parent: {order} (D)"
        outside = bool(self._annotation.outside[st.joint])
        w.outside_button.label = (
            "Outside the image: yes (O)" if outside else "Outside the image (O)"
        )
        data = self.frame_data
        w.message_md.content = f"**⚠ {data.error}**" if data is not None and data.error else ""
        colours, ann = self.hand.base_colours, self._annotation
        diagram = self._diagram_xy
        w.legend_md.content = (
            ""
            if diagram is None
            else hand_diagram_svg(diagram, self.skeleton.bones, colours, ann, st.joint)
        ) + joint_legend(self.skeleton.joint_names, colours, ann, st.joint)
        if not self.ctx.worker.available:
            w.lift_md.content = "*live lifting unavailable (handanno_core.lift missing)*"


class AnnotateClicks:
    """The Annotate panel's answers to the hand scene's pointer events (a
    :class:`~app.ui.hand_scene.ScenePanel`); see the module docstring for the rules."""

    def __init__(self, panel: AnnotatePanel):
        self.panel = panel

    def _ray_pixel(self, origin: np.ndarray, direction: np.ndarray) -> np.ndarray | None:
        data = self.panel.frame_data
        if data is None or data.depth is None:
            return None
        return data.geometry.ray_to_pixel(origin, direction)

    def on_image_click(self, origin: np.ndarray, direction: np.ndarray) -> JournalEntry | None:
        """A click ray on the image plane (mode 2D) -> the selected joint's 2D position."""
        uv = self._ray_pixel(origin, direction) if self.panel.state.click_mode == "2d" else None
        return None if uv is None else self.panel.edit(lambda: self.panel.state.place_2d(uv))

    def on_scene_click(self, origin: np.ndarray, direction: np.ndarray, shift: bool) -> None:
        """Mode 3D (or Shift): a placed joint's sphere selects it; anywhere else (guesses
        included) the selected joint snaps to the nearest cloud point along the ray."""
        if self.panel.state.click_mode != "3d" and not shift:
            return
        k = self.panel.hand.joint_hit(origin, direction)
        if k is not None:
            self.panel.select_joint(k)
            return
        data = self.panel.frame_data
        xyz = None if data is None else data.geometry.nearest_cloud_point(origin, direction)
        if xyz is not None:
            self.panel.edit(lambda: self.panel.state.place_3d(xyz))

    def on_joint_click(self, k, origin, direction, modifier) -> None:
        """Mode 2D (no modifier): places the selected joint's 2D position under the pointer (a
        neighbouring joint never swallows a click). Mode 3D or Shift: selects joint ``k``."""
        if modifier is None and self.panel.state.click_mode == "2d":
            uv = self._ray_pixel(origin, direction)
            if uv is not None:
                self.panel.edit(lambda: self.panel.state.place_2d(uv))
            return
        k = self.panel.hand.joint_hit(origin, direction) if k is None else k
        if k is not None:
            self.panel.select_joint(int(k))

    def can_drag(self, k: int) -> bool:
        """In mode 3D only the selected joint moves (grabbing another selects it)."""
        ok = not (self.panel.state.click_mode == "3d" and k != self.panel.state.joint)
        self.panel.select_joint(k)
        return ok

    def on_drop(self, k: int, xyz_mm: np.ndarray) -> None:
        self.panel.edit(lambda: self.panel.state.place_3d(xyz_mm, joint=k, advance=False))

    def on_ring_drop(self, k: int, uv_px: np.ndarray) -> None:
        self.panel.edit(lambda: self.panel.state.place_2d(uv_px, joint=k, advance=False))
