"""The "Review" view: one object per connected browser (a tab next to "Annotate").

Panel: "Propagate & refine" (runs in the background :class:`~app.review_state.ReviewRunner`, with
a progress bar; propagated skeletons appear while it runs; on a session annotated only in the
browser it first lifts the references and estimates the bone lengths), "Lift all references"
(that lift alone), a timeline slider with play/pause
(reference frames marked), the per-frame review score as a uPlot chart, "Next worst frame",
Accept / Flag (``SetReview``), export (JSON / NPZ / MSRA download) and JSON import.

Scene (client-scoped, under ``/review``, metres centred on the hand like the annotate view): the
frame's point cloud, its skeleton (one batched mesh, draggable) and bones. Both tabs live in the
same 3D scene, so the two views' nodes are toggled: the review scene shows as soon as the review
panel is used, and "Show annotate scene" switches back.

Dragging a joint of a propagated frame is a correction: one journal entry (a Batch) makes the frame
a reference (``correction=True``), seeds its annotation from the shown skeleton and moves the
joint; the runner then lifts it and re-propagates and re-refines only its descendants.

Server-wide state (the live results, the runner, the ticker that pushes progress to every page)
is one :class:`ReviewHub` per :class:`~app.server.AnnoServer` (``ReviewHub.of(app)``).
"""

from __future__ import annotations

import tempfile
import threading
import time
import traceback
import weakref
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import viser
import viser.uplot

from handanno_core.session import JournalEntry, SessionError, SetReview

from .annotate_view import joint_colours, load_colours
from .frames import FrameData
from .geometry import pull_in_front_of_surface
from .hotkeys import REVIEW_HOTKEYS, bind_all
from .review_state import LiveResults, ReviewRunner, correction_command, next_worst
from .scene_nodes import UNIT_SPHERE, add_bones, add_hand_cloud, add_joint_meshes, show_hand_cloud

if TYPE_CHECKING:
    from .server import AnnoServer

ROOT = "/review"
JOINT_RADIUS_M = 0.0045
STAGE_TEXT = {0: "not computed yet", 1: "lifted", 2: "propagated", 3: "refined"}
EXPORT_FORMATS = {"JSON": ("json", "json"), "NPZ": ("npz", "npz"), "MSRA": ("msra", "txt")}
_HUB_LOCK = threading.Lock()


class ReviewHub:
    """Server-wide review state: live results, the runner, and a ticker updating every review view."""

    def __init__(self, app: AnnoServer, runner_kwargs: dict[str, Any] | None = None):
        self.app = app
        self.session = app.session
        self.live = LiveResults(app.session)
        kwargs = dict(lift_for=self._lift_for)
        kwargs.update(runner_kwargs or getattr(app, "review_runner_kwargs", {}) or {})
        self.runner = ReviewRunner(app.session, self.live, **kwargs)
        self.runner.listeners.append(self._on_runner)
        self.views: weakref.WeakSet[ReviewView] = weakref.WeakSet()
        self._stop = threading.Event()
        self._ticker = threading.Thread(target=self._tick, name="handanno-review-ui", daemon=True)
        self._ticker.start()

    @classmethod
    def of(cls, app: AnnoServer) -> ReviewHub:
        with _HUB_LOCK:
            hub = getattr(app, "review_hub", None)
            if hub is None:
                hub = cls(app)
                app.review_hub = hub  # type: ignore[attr-defined]
            return hub

    def _lift_for(self, frame: int, seq: int, timeout_s: float = 300.0) -> np.ndarray | None:
        """Wait for the app's lift worker to lift ``frame`` at journal entry ``seq`` or later."""
        worker = self.app.worker
        if not worker.available:
            return None
        worker.submit(frame)
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            out = worker.latest.get(frame)
            if out is not None and out.journal_seq >= seq:
                return out.joints_mm
            time.sleep(0.05)
        return None

    def _on_runner(self, event: str, runner: ReviewRunner, frame: int) -> None:
        if event == "lifted":  # "lift all" replaced the references' lifted joints on disk
            self.app.worker.forget(self.session.reference_frames)
        elif event == "frame":
            for view in list(self.views):
                if view.frame == frame:
                    view.render_skeleton()
        elif event == "finished":
            for view in list(self.views):
                view.render_skeleton()
                view.refresh(force=True)

    def _tick(self) -> None:
        while not self._stop.wait(0.3):
            for view in list(self.views):
                try:
                    view.refresh()
                except Exception:
                    traceback.print_exc()

    def stop(self) -> None:
        self._stop.set()
        self.runner.stop()


class ReviewView:
    """Per-client review view; see the module docstring."""

    name = "Review"

    def __init__(self, app: AnnoServer, client: viser.ClientHandle):
        self.app = app
        self.client = client
        self.session = app.session
        self.hub = ReviewHub.of(app)
        self.live = self.hub.live
        self.runner = self.hub.runner
        self.skeleton = app.session.skeleton
        self.client_name = app.client_name(client)
        self._lock = threading.RLock()
        self.frame = 0
        self._frame_data: FrameData | None = None
        self._joints_mm = np.full((self.skeleton.num_joints, 3), np.nan)
        self._drag: tuple[int, np.ndarray, np.ndarray] | None = None
        self._playing = False
        self._play_thread: threading.Thread | None = None
        self._shown_version = -1
        self._shown_status: tuple = ()
        self.scene_active = False
        #: (entry seq, perf_counter at ack) of this client's review edits (benchmarks, tests)
        self.acks: list[tuple[int, float]] = []
        self.colours = load_colours()
        self.base_colours = joint_colours(self.skeleton.parent_array, self.colours)
        self._build_scene()
        self._build_gui()
        self.hub.views.add(self)
        self.show_frame(0)
        self.refresh(force=True)

    # ================================================================== construction
    def _build_scene(self) -> None:
        scene = self.client.scene
        self.cloud = add_hand_cloud(scene, f"{ROOT}/cloud", visible=False)
        self.joints = add_joint_meshes(
            scene, f"{ROOT}/joints", UNIT_SPHERE, self.base_colours, visible=False
        )
        self.bones = add_bones(
            scene, f"{ROOT}/bones", self.skeleton.bones, self.base_colours, visible=False
        )

        @self.joints.on_drag("left")
        async def _(event: viser.SceneNodeDragEvent) -> None:
            self._on_drag(event)

    def _build_gui(self) -> None:
        gui = self.client.gui
        n = self.session.num_frames
        self.status_md = gui.add_markdown("")
        self.run_button = gui.add_button(
            "Propagate & refine", hint="Propagate every frame, then refine (background)"
        )
        self.lift_button = gui.add_button(
            "Lift all references",
            hint="Lift every annotated reference to 3D and estimate the bone lengths (background)",
        )
        self.cancel_button = gui.add_button("Cancel run", color="red", disabled=True)
        self.run_bar = gui.add_progress_bar(0.0, animated=False)
        self.run_md = gui.add_markdown("*no run yet*")
        refs = [int(f) for f in self.session.reference_frames]
        marks = tuple((f, "") for f in refs[:60]) if refs else None
        self.slider = gui.add_slider(
            "Frame", min=0, max=max(n - 1, 1), step=1, initial_value=0, marks=marks
        )
        self.play_nav = gui.add_button_group("Playback", ("◀", "Play", "▶"))
        self.worst_button = gui.add_button(
            "Next worst frame", hint="Walk frames by increasing review score"
        )
        self.review_buttons = gui.add_button_group("Review", ("Accept", "Flag", "Clear"))
        self.frame_md = gui.add_markdown("")
        x = np.arange(n, dtype=np.float64)
        self.plot = gui.add_uplot(
            data=(x, np.zeros(n), np.zeros(n)),
            series=(
                viser.uplot.Series(label="frame"),
                viser.uplot.Series(label="score", stroke="#1f77b4", width=1.5),
                viser.uplot.Series(
                    label="current", stroke="#d62728", width=2, points={"show": False}
                ),
            ),
            scales={"x": {"time": False}, "y": {"range": [0.0, 1.05]}},
            title="Review score (1 = trustworthy)",
            aspect=2.0,
        )
        self.scene_button = gui.add_button(
            "Show annotate scene", hint="Both tabs share the 3D scene"
        )
        with gui.add_folder("Export / import", expand_by_default=False):
            self.export_buttons = gui.add_button_group("Export", tuple(EXPORT_FORMATS))
            self.import_button = gui.add_upload_button("Import JSON", mime_type="application/json")
            self.io_md = gui.add_markdown("")
        self.saved_md = gui.add_markdown("")

        @self.run_button.on_click
        def _(_: Any) -> None:
            self.activate_scene()
            self.start_run()

        @self.lift_button.on_click
        def _(_: Any) -> None:
            self.start_lift()

        @self.cancel_button.on_click
        def _(_: Any) -> None:
            self.runner.cancel()

        @self.slider.on_update
        def _(event: Any) -> None:
            if event.client is not None and int(self.slider.value) != self.frame:
                self.activate_scene()
                self.show_frame(int(self.slider.value))

        @self.play_nav.on_click
        def _(event: Any) -> None:
            self.activate_scene()
            value = event.target.value
            if value == "◀":
                self.show_frame(self.frame - 1)
            elif value == "▶":
                self.show_frame(self.frame + 1)
            else:
                self.toggle_play()

        @self.worst_button.on_click
        def _(_: Any) -> None:
            self.activate_scene()
            self.go_worst()

        @self.review_buttons.on_click
        def _(event: Any) -> None:
            {"Accept": self.accept, "Flag": self.flag, "Clear": lambda: self.set_review(None)}[
                event.target.value
            ]()

        self._told_hotkeys = False
        bind_all(
            gui,
            {
                "review_accept": self._hotkey(self.accept),
                "review_flag": self._hotkey(self.flag),
                "review_next_worst": self._hotkey(self.go_worst),
            },
            REVIEW_HOTKEYS,
        )

        @self.scene_button.on_click
        def _(_: Any) -> None:
            if self.scene_active:
                self.deactivate_scene()
            else:
                self.activate_scene()

        @self.export_buttons.on_click
        def _(event: Any) -> None:
            self.export(event.target.value)

        @self.import_button.on_upload
        def _(event: Any) -> None:
            self.import_upload(event.target.value.name, event.target.value.content)

    # ================================================================== scene switching
    def _annotate_handles(self) -> list[Any]:
        with self.app._views_lock:
            view = self.app.views.get(self.client.client_id, {}).get("Annotate")
        if view is None:
            return []
        return [
            getattr(view, n, None)
            for n in ("cloud", "image", "handles2d", "joints", "guesses", "bones")
        ] + list(getattr(view, "labels", []))

    def activate_scene(self) -> None:
        """Show the review scene (and hide the annotate view's nodes) in this browser."""
        if self.scene_active:
            return
        self.scene_active = True
        with self.client.atomic():
            for h in self._annotate_handles():
                if h is not None:
                    h.visible = False
            self.cloud.visible = (
                self._frame_data is not None and len(self._frame_data.geometry.cloud_mm) > 0
            )
            self.joints.visible = True
            self.bones.visible = True
        self.scene_button.label = "Show annotate scene"
        self.reset_camera()

    def deactivate_scene(self) -> None:
        self.scene_active = False
        with self.client.atomic():
            self.cloud.visible = False
            self.joints.visible = False
            self.bones.visible = False
            for h in self._annotate_handles()[:6]:
                if h is not None:
                    h.visible = True
        self.scene_button.label = "Show review scene"
        view = self.app.views.get(self.client.client_id, {}).get("Annotate")
        if view is not None:
            view.show_frame(view.frame)

    def reset_camera(self) -> None:
        data = self._frame_data
        if data is None:
            return
        cam = self.session.camera
        with self.client.atomic():
            self.client.camera.up_direction = (0.0, -1.0, 0.0)
            self.client.camera.fov = float(2.0 * np.arctan(cam.height / 2.0 / cam.fy))
            self.client.camera.position = data.geometry.sensor_position
            self.client.camera.look_at = (0.0, 0.0, 0.0)

    # ================================================================== navigation
    def show_frame(self, frame: int) -> None:
        frame = int(np.clip(frame, 0, self.session.num_frames - 1))
        data = self.app.frames.get(frame)
        geo = data.geometry
        with self._lock, self.client.atomic():
            self.frame = frame
            self._frame_data = data
            self.cloud.visible = show_hand_cloud(self.cloud, geo) and self.scene_active
            if int(self.slider.value) != frame:
                self.slider.value = frame
        self.render_skeleton()
        self.refresh(force=True)

    def toggle_play(self) -> None:
        self._playing = not self._playing
        self.play_nav.options = ("◀", "Pause" if self._playing else "Play", "▶")
        if self._playing and (self._play_thread is None or not self._play_thread.is_alive()):
            self._play_thread = threading.Thread(
                target=self._play, name="handanno-review-play", daemon=True
            )
            self._play_thread.start()

    def _play(self, fps: float = 8.0) -> None:
        while self._playing:
            t0 = time.monotonic()
            try:
                self.show_frame((self.frame + 1) % self.session.num_frames)
            except Exception:
                self._playing = False
                return
            time.sleep(max(0.0, 1.0 / fps - (time.monotonic() - t0)))

    def _hotkey(self, action: Any) -> Any:
        """Review hotkeys act on the Review scene only (say so once otherwise)."""

        def run(_client: Any) -> None:
            if self.scene_active:
                action()
            elif not self._told_hotkeys:
                self._told_hotkeys = True
                self.client.add_notification(
                    "Review hotkeys",
                    "A / F / W act while the Review scene is shown (use the Review panel first).",
                    auto_close_seconds=6.0,
                )

        return run

    def step_frame(self, step: int) -> None:
        """Previous / next frame of the review timeline (hotkeys P / N on the Review scene)."""
        self.show_frame(self.frame + step)

    def accept(self) -> JournalEntry | None:
        """Accept the shown frame, then go on to the next worst frame."""
        entry = self.set_review("accepted")
        if entry is not None:
            self.go_worst()
        return entry

    def flag(self) -> JournalEntry | None:
        return self.set_review("flagged")

    def go_worst(self) -> int | None:
        """Go to the next frame by increasing review score (accepted frames and references skipped)."""
        scores = self.live.scores().score
        accepted = [int(k) for k, v in self.session.model.review.items() if v == "accepted"]
        exclude = set(accepted) | {int(f) for f in self.session.reference_frames}
        frame = next_worst(scores, self.frame, exclude)
        if frame is None:
            self.client.add_notification(
                "Nothing to review", "no propagated frames yet", auto_close_seconds=3.0
            )
            return None
        self.show_frame(frame)
        return frame

    # ================================================================== edits
    def set_review(self, status: str | None) -> JournalEntry | None:
        return self._execute(
            lambda: self.session.execute(
                SetReview(frame=self.frame, status=status), self.client_name
            )
        )

    def move_joint(self, joint: int, xyz_mm: np.ndarray) -> JournalEntry | None:
        """Review edit: move ``joint`` of the shown frame to ``xyz_mm`` (a correction on a
        propagated frame; see :func:`~app.review_state.correction_command`)."""
        frame = self.frame
        shown = self._joints_mm.copy()
        if not np.all(np.isfinite(shown)):
            self.client.add_notification(
                "Nothing to correct", "this frame has no skeleton yet", color="yellow"
            )
            return None
        depth = self._frame_data.depth if self._frame_data is not None else None

        def run() -> JournalEntry:
            with self.session.lock:  # decide "seed or not" and execute atomically (two annotators)
                command, _ = correction_command(self.session, frame, joint, xyz_mm, shown, depth)
                return self.session.execute(command, self.client_name)

        entry = self._execute(run)
        if entry is not None:
            self.runner.request_correction(frame, entry.seq)
        return entry

    def _execute(self, action) -> JournalEntry | None:
        try:
            entry = action()
        except SessionError as exc:
            self.client.add_notification("Edit NOT saved", str(exc), color="red")
            return None
        except ValueError as exc:
            self.client.add_notification(
                "Edit refused", str(exc), color="yellow", auto_close_seconds=5.0
            )
            return None
        self.acks.append((entry.seq, time.perf_counter()))
        stamp = time.strftime("%H:%M:%S", time.localtime(entry.time))
        self.saved_md.content = f"✓ review saved {stamp} (#{entry.seq})"
        self.refresh(force=True)
        return entry

    def _on_drag(self, event: viser.SceneNodeDragEvent) -> None:
        k = event.instance_index
        data = self._frame_data
        if k is None or data is None:
            return
        if event.phase == "start":
            drawn = data.geometry.to_scene(self._display_mm(self._joints_mm))
            if not np.all(np.isfinite(drawn[k])):
                return
            true = data.geometry.to_scene(self._joints_mm[k])
            self._drag = (int(k), drawn[k] - np.asarray(event.start_position), true - drawn[k])
            return
        if self._drag is None or self._drag[0] != k:
            return
        new = np.asarray(event.end_position) + self._drag[1]
        if event.phase == "update":
            with self._lock:
                pos = np.asarray(self.joints.batched_positions, dtype=np.float64).copy()
                pos[k] = new
                self.joints.batched_positions = pos.astype(np.float32)
            return
        _, _, depth_offset = self._drag
        self._drag = None
        xyz = data.geometry.from_scene(new + depth_offset)
        if xyz[2] > 0:
            self.move_joint(int(k), xyz)

    # ================================================================== import / export
    def export(self, label: str) -> None:
        from handanno_core.export import export_bytes

        fmt, ext = EXPORT_FORMATS[label]
        try:
            data = export_bytes(self.session, fmt)
        except Exception as exc:
            self.client.add_notification(
                "Export failed", f"{type(exc).__name__}: {exc}", color="red"
            )
            return
        name = (
            f"{self.session.model.name}-{fmt}.{ext}"
            if fmt == "msra"
            else f"{self.session.model.name}.{ext}"
        )
        self.client.send_file_download(name, data, save_immediately=True)
        self.io_md.content = f"exported {label} ({len(data) / 1024:.0f} KiB)"

    def import_upload(self, name: str, content: bytes) -> int | None:
        """Import an uploaded JSON export (written to a temporary file; the upload's name is never
        used as a path)."""
        from handanno_core.export import import_json

        with tempfile.TemporaryDirectory(prefix="handanno-import-") as tmp:
            path = Path(tmp) / "upload.json"
            path.write_bytes(content)
            try:
                count = import_json(self.session, path, client=self.client_name)
            except (SessionError, ValueError, KeyError) as exc:
                msg = str(exc).replace(str(path), name)
                self.client.add_notification("Import failed", msg, color="red")
                self.io_md.content = f"**import failed:** {msg}"
                return None
        self.live.reload()
        self.io_md.content = f"imported {count} frames from {name}"
        self.client.add_notification(
            "Imported", f"{count} frames from {name}", auto_close_seconds=4.0
        )
        self.show_frame(self.frame)
        return count

    # ================================================================== session events
    def on_entry(self, entry: JournalEntry, frame: int) -> None:
        """A journal entry was acknowledged (any client; called under the session lock)."""
        if frame == self.frame and entry.client != self.client_name:
            self.client.add_notification(
                "Frame edited elsewhere",
                f"another annotator changed frame {frame}",  # never another client's id (issue 16)
                color="blue",
                auto_close_seconds=4.0,
            )

    def on_lift(self, outcome: Any) -> None:
        """The lift worker lifted a frame: a review-made reference shows its new skeleton."""
        if outcome.joints_mm is None or int(outcome.frame) not in set(
            self.session.model.corrections
        ):
            return
        self.live.put(int(outcome.frame), outcome.joints_mm, None, 1)
        if outcome.frame == self.frame:
            self.render_skeleton()

    # ================================================================== drawing
    def _display_mm(self, joints_mm: np.ndarray) -> np.ndarray:
        """Joints behind the observed surface are drawn pulled along their camera ray to just in
        front of it (same rule as the annotate view), so the cloud does not hide them."""
        data = self._frame_data
        depth = None if data is None else data.depth
        return pull_in_front_of_surface(joints_mm, depth, self.session.camera)

    def render_skeleton(self) -> None:
        data = self._frame_data
        if data is None:
            return
        joints, stage = self.live.frame(self.frame)
        self._joints_mm = joints
        shown = np.all(np.isfinite(joints), axis=1)
        pos = np.where(
            shown[:, None], data.geometry.to_scene(self._display_mm(joints)), 0.0
        ).astype(np.float32)
        is_ref = self.frame in set(self.session.model.selection.reference_frames)
        scales = np.where(shown, JOINT_RADIUS_M * (1.3 if is_ref else 1.0), 0.0).astype(np.float32)
        bones = self.skeleton.bones
        seg = np.where(shown[bones].all(axis=1)[:, None, None], pos[bones], 0.0).astype(np.float32)
        with self._lock, self.client.atomic():
            if self._drag is None:
                self.joints.batched_positions = pos
            self.joints.batched_scales = scales
            self.bones.points = seg

    def refresh(self, force: bool = False) -> None:
        """Update the panel (run progress, frame text, score plot) if anything changed."""
        st = self.runner.status
        status = (st.phase, st.done, st.total, st.message, self.frame, self.live.version)
        if not force and status == self._shown_status:
            return
        self._shown_status = status
        n = self.session.num_frames
        filled = self.live.filled()
        with self._lock:
            self.run_bar.value = float(st.percent) if st.phase != "idle" else 0.0
            self.run_button.disabled = st.running
            self.lift_button.disabled = st.running
            self.cancel_button.disabled = not st.running
            self.run_md.content = f"{st.text()} · {filled} of {n} frames have a skeleton"
            self.status_md.content = (
                f"**{len(self.session.model.selection.reference_frames)} references** "
                f"({len(self.session.model.corrections)} from review corrections)"
            )
        self._refresh_frame_text()
        if force or self.live.version != self._shown_version:
            self._shown_version = self.live.version
            self._refresh_plot()

    def _refresh_frame_text(self) -> None:
        _, stage = self.live.frame(self.frame)
        scores = self.live.scores().score
        is_ref = self.frame in set(self.session.model.selection.reference_frames)
        review = self.session.model.review.get(str(self.frame))
        score = scores[self.frame]
        bits = ["reference" if is_ref else STAGE_TEXT[stage]]
        if np.isfinite(score) and not is_ref:
            bits.append(f"score {score:.2f}")
        if review:
            bits.append(review)
        self.frame_md.content = f"**Review frame {self.frame}** ({', '.join(bits)})"

    def _refresh_plot(self) -> None:
        n = self.session.num_frames
        score = np.nan_to_num(self.live.scores().score, nan=0.0)
        marker = np.where(np.arange(n) == self.frame, 1.05, 0.0)
        self.plot.data = (np.arange(n, dtype=np.float64), score, marker)

    def start_run(self) -> bool:
        if not self.runner.start_full():
            self.client.add_notification(
                "Already running", "a propagation run is in progress", auto_close_seconds=3.0
            )
            return False
        self.refresh(force=True)
        return True

    def start_lift(self) -> bool:
        if not self.runner.start_lift():
            self.client.add_notification(
                "Already running", "a run is in progress", auto_close_seconds=3.0
            )
            return False
        self.refresh(force=True)
        return True

    def close(self) -> None:
        self._playing = False
        self.hub.views.discard(self)
