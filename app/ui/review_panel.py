"""The Review tab: its widgets, their callbacks, and how it draws the shared hand scene.

Panel: "Propagate & refine" (the context's background :class:`~app.control.jobs.ReviewRunner`,
with a progress bar; propagated skeletons appear while it runs), "Lift all references", a
timeline slider with play/pause (reference frames marked, up to :data:`MAX_MARKS` of them), the
review priority as a uPlot chart (the shown frame is a marker point, not a line), "Next worst
frame", Accept / Flag / Clear, "Show labels" and "Show depth image", export (JSON / NPZ / MSRA
download) and JSON import.

Sized for long sessions (76,000 frames): the chart has at most about :data:`PLOT_POINTS` points,
one per frame below that, else the worst priority of each bin of consecutive frames
(:func:`handanno_core.aggregate.summarize_bins`, bins cut at sequence breaks); it is redrawn only
when the background ranking is new or the shown frame moves to another bin, and nothing here
ranks frames (the context's :class:`~app.control.live.LiveResults` ranks in the background).

Dragging a joint of a propagated frame is a correction (:meth:`ReviewState.move_joint`). Every
action is a method of :class:`~app.control.review.ReviewState`; this module only shows results.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import viser.uplot

from handanno_core.aggregate import bin_edges, summarize_bins
from handanno_core.session import JournalEntry, SessionError

from ..control.events import Update, UpdateTopic
from ..control.frames import FrameData
from ..control.review import EXPORT_FORMATS, frame_text
from .hand_scene import Drawing

if TYPE_CHECKING:
    from .client_ui import ClientUI

#: the priority chart's number of points (bins of consecutive frames beyond it)
PLOT_POINTS = 1000
#: reference frames marked on the timeline slider (none in sessions with more references)
MAX_MARKS = 60


@dataclass
class ReviewWidgets:
    status_md: Any
    run_button: Any
    lift_button: Any
    cancel_button: Any
    run_bar: Any
    run_md: Any
    slider: Any
    play_nav: Any
    worst_button: Any
    review_buttons: Any
    frame_md: Any
    plot: Any
    scene_button: Any
    labels: Any
    image: Any
    export_buttons: Any
    import_button: Any
    io_md: Any
    saved_md: Any


def make_review_widgets(gui: Any, n: int, refs: list[int], edges: np.ndarray) -> ReviewWidgets:
    """The widgets; ``edges`` (K+1,): the frame bins of the priority chart."""
    x = edges[:-1].astype(np.float64)
    k = len(x)
    status_md = gui.add_markdown("")
    run_button = gui.add_button(
        "Propagate & refine", hint="Propagate every frame, then refine (background)"
    )
    lift_button = gui.add_button(
        "Lift all references",
        hint="Lift every annotated reference to 3D and estimate the bone lengths (background)",
    )
    cancel_button = gui.add_button("Cancel run", color="red", disabled=True)
    run_bar, run_md = gui.add_progress_bar(0.0, animated=False), gui.add_markdown("*no run yet*")
    marks = tuple((f, "") for f in refs) if 0 < len(refs) <= MAX_MARKS else None
    slider = gui.add_slider("Frame", min=0, max=max(n - 1, 1), step=1, initial_value=0, marks=marks)
    play_nav = gui.add_button_group("Playback", ("◀", "Play", "▶"))
    worst_button = gui.add_button(
        "Next worst frame", hint="The unreviewed frame the evidence ranking trusts least"
    )
    review_buttons = gui.add_button_group("Review", ("Accept", "Flag", "Clear"))
    frame_md = gui.add_markdown("")
    plot = gui.add_uplot(
        data=(x, np.zeros(k), np.full(k, np.nan)),
        series=(
            viser.uplot.Series(label="frame"),
            viser.uplot.Series(label="priority", stroke="#1f77b4", width=1.5),
            viser.uplot.Series(
                label="shown frame", stroke="#d62728", width=0,
                points={"show": True, "size": 9, "fill": "#d62728"},
            ),
        ),
        scales={"x": {"time": False}, "y": {"range": [0.0, 1.1]}},
        title="Review priority (1 = look first)",
        aspect=2.0,
    )  # fmt: skip
    scene_button = gui.add_button("Show annotate scene", hint="Both tabs share the 3D scene")
    labels = gui.add_checkbox("Show labels", False)
    image = gui.add_checkbox("Show depth image", False)
    with gui.add_folder("Export / import", expand_by_default=False):
        export_buttons = gui.add_button_group("Export", tuple(EXPORT_FORMATS))
        import_button = gui.add_upload_button("Import JSON", mime_type="application/json")
        io_md = gui.add_markdown("")
    saved_md = gui.add_markdown("")
    return ReviewWidgets(
        status_md, run_button, lift_button, cancel_button, run_bar, run_md, slider, play_nav,
        worst_button, review_buttons, frame_md, plot, scene_button, labels, image, export_buttons,
        import_button, io_md, saved_md,
    )  # fmt: skip


class PriorityChart:
    """The review priority chart: the worst priority of each bin of frames ``edges`` (K+1,)
    (normalized, 1 = look first) and the shown frame's bin as a marker point."""

    def __init__(self, plot: Any, edges: np.ndarray, live: Any):
        self.plot, self.edges, self.live = plot, edges, live
        self.shown: tuple[int, int] = (-2, -1)  # (ranking version, marker bin) on the chart
        self.y: tuple[int, np.ndarray] = (-2, np.zeros(len(edges) - 1))  # per-bin maxima

    def show(self, frame: int) -> None:
        """Redraw if the ranking or ``frame``'s bin changed: O(K) for K bins, plus O(N) numpy
        once per new ranking (never a ranking: the newest one the live results have)."""
        edges = self.edges
        shown = (self.live.ranked_version(), int(np.searchsorted(edges, frame, "right") - 1))
        if shown == self.shown:
            return
        if self.y[0] != shown[0]:
            p = self.live.ranking(wait_s=0.0)
            y = np.zeros(len(edges) - 1)
            if p is not None and np.isfinite(p).any():
                top = np.nanmax(p)
                y = np.nan_to_num(summarize_bins(p / top if top > 0 else p, edges).max, nan=0.0)
            self.y = (shown[0], y)
        marker = np.full(len(edges) - 1, np.nan)
        marker[shown[1]] = 1.05
        self.plot.data = (edges[:-1].astype(np.float64), self.y[1], marker)
        self.shown = shown


class ReviewPanel:
    """The Review tab of one browser; see the module docstring."""

    def __init__(self, ui: ClientUI):
        self.ui = ui
        self.ctx = ui.ctx
        self.client = ui.client
        self.session = ui.ctx.session
        self.hand = ui.scene
        self.live = ui.ctx.live
        self.runner = ui.ctx.runner
        self.state = ui.ctx.review_state(ui.name)
        refs = [int(f) for f in self.session.reference_frames]
        n = self.session.num_frames
        edges = bin_edges(n, PLOT_POINTS, self.session.model.sequence_breaks)
        self.w = make_review_widgets(self.client.gui, n, refs, edges)
        self.chart = PriorityChart(self.w.plot, edges, self.live)
        self.frame_data: FrameData | None = None
        self._joints_mm = np.full((self.session.skeleton.num_joints, 3), np.nan)
        self._playing = False
        #: (entry seq, perf_counter at ack) of this client's review edits (benchmarks, tests)
        self.acks: list[tuple[int, float]] = []
        self._bind()
        self.refresh()

    @property
    def frame(self) -> int:
        return self.state.frame

    @property
    def scene_active(self) -> bool:
        return self.ui.state.active_scene == "review"

    def _bind(self) -> None:
        w, ui = self.w, self.ui

        def shown(fn):  # using the panel shows its scene
            def run(*_: Any) -> None:
                ui.show("review")
                fn()

            return run

        w.run_button.on_click(shown(self.start_run))
        w.lift_button.on_click(lambda _: self.start_lift())
        w.cancel_button.on_click(lambda _: self.runner.cancel())
        w.slider.on_update(
            lambda e: (
                e.client is not None
                and int(w.slider.value) != self.frame
                and shown(lambda: self.show_frame(int(w.slider.value)))()
            )
        )
        w.play_nav.on_click(lambda e: shown(lambda: self._play_nav(e.target.value))())
        w.worst_button.on_click(shown(self.go_worst))
        w.review_buttons.on_click(
            lambda e: {"Accept": self.accept, "Flag": self.flag, "Clear": self.clear}[e.target.value]()
        )  # fmt: skip
        w.scene_button.on_click(lambda _: ui.show("annotate"))
        w.labels.on_update(lambda _: ui.post(self.render_skeleton))
        w.image.on_update(lambda _: self.hand.show_image(bool(w.image.value) and self.scene_active))
        w.export_buttons.on_click(lambda e: self.export(e.target.value))
        w.import_button.on_upload(
            lambda e: self.import_upload(e.target.value.name, e.target.value.content)
        )

    def _play_nav(self, value: str) -> None:
        if value == "◀":
            self.step_frame(-1)
        elif value == "▶":
            self.step_frame(+1)
        else:
            self.toggle_play()

    # ================================================================== scene
    def activate(self, reset_camera: bool = False) -> None:
        """This panel's scene is shown: draw it (on the UI thread)."""
        self._show_frame(self.frame, reset_camera)

    def deactivated(self) -> None:
        self._playing = False

    def show_frame(self, frame: int) -> None:
        self.state.go_to(frame)
        self.ui.post(self._show_frame, self.state.frame, False)

    def _show_frame(self, frame: int, reset_camera: bool) -> None:
        if frame != self.frame or not self.scene_active:
            return
        self.frame_data = self.ctx.frames.get(frame)
        self.hand.show_frame(self.frame_data, None, image=bool(self.w.image.value))
        if reset_camera:
            self.hand.reset_camera()
        if int(self.w.slider.value) != frame:
            self.w.slider.value = frame
        self.render_skeleton()
        self.refresh()

    def render_skeleton(self) -> None:
        if self.frame_data is None or not self.scene_active:
            return
        joints, _ = self.live.frame(self.frame)
        self._joints_mm = joints
        shown = np.all(np.isfinite(joints), axis=1)
        is_ref = self.frame in set(self.session.model.selection.reference_frames)
        self.hand.draw(
            Drawing(
                joints, placed=shown, guessed=np.zeros_like(shown),
                labels=bool(self.w.labels.value), scale=1.3 if is_ref else 1.0,
            )
        )  # fmt: skip

    # scene events: only joint drags are review edits
    def on_image_click(self, origin: np.ndarray, direction: np.ndarray) -> None:
        pass

    def on_scene_click(self, origin: np.ndarray, direction: np.ndarray, shift: bool) -> None:
        pass

    def on_joint_click(self, k, origin, direction, modifier) -> None:
        pass

    def can_drag(self, k: int) -> bool:
        return True

    def on_drop(self, k: int, xyz_mm: np.ndarray) -> None:
        self.move_joint(k, xyz_mm)

    def on_ring_drop(self, k: int, uv_px: np.ndarray) -> None:
        pass

    # ================================================================== navigation
    def step_frame(self, step: int) -> None:
        """Previous / next frame of the review timeline (hotkeys P / N on the Review scene)."""
        self.show_frame(self.frame + step)

    def toggle_play(self) -> None:
        self._playing = not self._playing
        self.w.play_nav.options = ("◀", "Pause" if self._playing else "Play", "▶")
        if self._playing:
            threading.Thread(target=self._play, name="handanno-review-play", daemon=True).start()

    def _play(self, fps: float = 8.0) -> None:
        while self._playing:
            t0 = time.monotonic()
            self.show_frame((self.frame + 1) % self.session.num_frames)
            time.sleep(max(0.0, 1.0 / fps - (time.monotonic() - t0)))

    def go_worst(self) -> int | None:
        if self.live.ranking(wait_s=0.0) is None:  # just opened: the first ranking is not ready
            self.client.add_notification(
                "Ranking frames",
                f"ranking {self.session.num_frames} frames for review; the worst one follows",
                auto_close_seconds=4.0,
            )
            threading.Thread(target=self._go_worst, name="handanno-worst", daemon=True).start()
            return None
        return self._go_worst()

    def _go_worst(self) -> int | None:
        frame = self.state.next_worst()
        if frame is None:
            self.client.add_notification(
                "Nothing to review", "no unreviewed propagated frame left", auto_close_seconds=3.0
            )
            return None
        self.show_frame(frame)
        return frame

    # ================================================================== edits
    def accept(self) -> JournalEntry | None:
        """Accept the shown frame, then go on to the next worst frame."""
        entry = self._execute(self.state.accept)
        self.show_frame(self.frame)
        return entry

    def flag(self) -> JournalEntry | None:
        return self._execute(self.state.flag)

    def clear(self) -> JournalEntry | None:
        return self._execute(lambda: self.state.set_review(None))

    def move_joint(self, joint: int, xyz_mm: np.ndarray) -> JournalEntry | None:
        depth = self.frame_data.depth if self.frame_data is not None else None
        return self._execute(
            lambda: self.state.move_joint(joint, xyz_mm, self._joints_mm.copy(), depth)
        )

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
        self.w.saved_md.content = f"✓ review saved {stamp} (#{entry.seq})"
        self.ui.post(self.refresh)
        return entry

    def export(self, label: str) -> None:
        try:
            name, data = self.state.export_bytes(label)
        except Exception as exc:
            self.client.add_notification(
                "Export failed", f"{type(exc).__name__}: {exc}", color="red"
            )
            return
        self.client.send_file_download(name, data, save_immediately=True)
        self.w.io_md.content = f"exported {label} ({len(data) / 1024:.0f} KiB)"

    def import_upload(self, name: str, content: bytes) -> int | None:
        try:
            count = self.state.import_upload(name, content)
        except (SessionError, ValueError) as exc:
            msg = str(exc)
            self.client.add_notification("Import failed", msg, color="red")
            self.w.io_md.content = f"**import failed:** {msg}"
            return None
        self.w.io_md.content = f"imported {count} frames from {name}"
        self.client.add_notification(
            "Imported", f"{count} frames from {name}", auto_close_seconds=4.0
        )
        self.show_frame(self.frame)
        return count

    def start_run(self) -> bool:
        return self._start(self.runner.start_full, "a propagation run is in progress")

    def start_lift(self) -> bool:
        return self._start(self.runner.start_lift, "a run is in progress")

    def _start(self, start, busy: str) -> bool:
        if not start():
            self.client.add_notification("Already running", busy, auto_close_seconds=3.0)
            return False
        self.ui.post(self.refresh)
        return True

    # ================================================================== updates
    def on_update(self, update: Update) -> None:
        """An :class:`Update` from the bus (on the UI thread)."""
        if UpdateTopic.RESULTS in update.topics or UpdateTopic.LIFT in update.topics:
            if update.frame in (-1, self.frame):
                self.render_skeleton()
        if update.topics & {
            UpdateTopic.REVIEW, UpdateTopic.REFERENCES, UpdateTopic.JOB, UpdateTopic.RANKING,
        }:  # fmt: skip
            self.refresh()
        if (
            UpdateTopic.ANNOTATION in update.topics
            and update.frame == self.frame
            and update.client != self.state.client
            and self.scene_active
        ):
            self.client.add_notification(
                "Frame edited elsewhere", f"another annotator changed frame {update.frame}",
                color="blue", auto_close_seconds=4.0,
            )  # fmt: skip

    def refresh(self) -> None:
        """Update the panel (run progress, frame text, priority chart: redrawn when the ranking
        is new or the shown frame's bin changed)."""
        st, w = self.runner.status, self.w
        n = self.session.num_frames
        w.run_bar.value = float(st.percent) if st.phase != "idle" else 0.0
        w.run_button.disabled = st.running
        w.lift_button.disabled = st.running
        w.cancel_button.disabled = not st.running
        w.run_md.content = f"{st.text()} · {self.live.filled()} of {n} frames have a skeleton"
        w.status_md.content = (
            f"**{len(self.session.model.selection.reference_frames)} references** "
            f"({len(self.session.model.corrections)} from review corrections)"
        )
        _, stage = self.live.frame(self.frame)
        is_ref = self.frame in set(self.session.model.selection.reference_frames)
        review = self.session.model.review.get(str(self.frame))
        w.frame_md.content = frame_text(
            self.frame, stage, is_ref, self.live.source(self.frame), review
        )
        self.chart.show(self.frame)

    def close(self) -> None:
        self._playing = False
