"""End-to-end: the app on a large session (issue 19) in real Chromium.

20,000 frames made cheaply (``tests/large_session.py``: 500 gesture folders linking the 40 frames
of the e2e sequence, a crop cache of 32 x 32 crops, results arrays of N frames from ground truth
plus noise; nothing rendered or propagated), so the Review tab's timeline, its aggregated priority
chart and the next-worst walk run on arrays of N frames. Behaviour only: how fast each action is
answered is measured by ``benchmarks/bench_app_scale.py``, not asserted here.
"""

from __future__ import annotations

import numpy as np
import pytest
from large_session import build_large_session
from viser_helpers import browser, free_port, journal, open_app, wait_until

from app.control import live as live_module
from app.control.review import NEIGHBOUR_RADIUS
from app.ui.review_panel import PLOT_POINTS
from app.ui.server import serve
from handanno_core.prefill import cached_crops
from handanno_core.review import rank_priority
from handanno_core.session import Session

COPIES = 500  # x 40 frames


@pytest.fixture(scope="module")
def large(synthetic_data, tmp_path_factory):
    folder = tmp_path_factory.mktemp("e2e-large") / "sess"
    build_large_session(folder, synthetic_data, COPIES, crop_size=32)
    # the finger ambiguity (about 27 ms per frame, filled in over many rankings) is off here: this
    # test walks the ranking of N frames; tests/test_app_control.py covers the ambiguity filling in
    mp = pytest.MonkeyPatch()
    mp.setattr(live_module, "AMBIGUITY_FRAMES_PER_RANKING", 0)
    with Session.open(folder) as s:  # the ranking the app must walk, computed here on its own
        expected = rank_priority(
            "evidence", s, s.load_results(), cached_crops(s),
            ambiguity=np.full(s.num_frames, np.nan),
        )  # fmt: skip
        expected[s.reference_frames] = np.nan
    app = serve(folder, port=free_port(), block=False)
    try:
        with browser() as b:
            page = open_app(b, app.url)
            wait_until(lambda: app.review_panels(), what="the review view")
            page.get_by_role("tab", name="Review").click()
            page.get_by_role("button", name="Next worst frame").wait_for(timeout=60_000)
            yield app, page, folder, expected
    finally:
        app.stop()
        mp.undo()


def _frame_shown(page, view, frame: int) -> bool:
    return view.frame == frame and page.get_by_text(f"Review frame {frame} (").is_visible()


def test_the_timeline_moves_to_the_frame_chosen_on_the_slider(large):
    app, page, _, _ = large
    view = app.review_panels()[0]
    n = view.session.num_frames
    assert n == COPIES * 40
    thumb = page.locator('[role="slider"]:visible')
    track = page.locator(".mantine-Slider-root:visible").bounding_box()
    assert thumb.count() == 1 and track is not None
    for share in (0.7, 0.25):
        page.mouse.click(track["x"] + share * track["width"], track["y"] + track["height"] / 2)
        value = wait_until(
            lambda: (v := int(thumb.get_attribute("aria-valuenow"))) == view.frame and v,
            what="the server to follow the slider",
        )
        assert abs(value - share * (n - 1)) < 0.05 * n, "the click landed far from the slider spot"
        wait_until(lambda v=value: _frame_shown(page, view, v), what=f"frame {value} shown")
    thumb.focus()
    page.keyboard.press("End")
    wait_until(lambda: _frame_shown(page, view, n - 1), what="the last frame shown")
    # the priority chart is aggregated: at most PLOT_POINTS bins (+ sequence breaks), the marker
    # on the bin of the shown frame
    x, y, marker = (np.asarray(a) for a in view.w.plot.data)
    assert len(x) <= PLOT_POINTS + len(view.session.model.sequence_breaks) < n
    assert np.flatnonzero(np.isfinite(marker)).tolist() == [len(x) - 1]
    wait_until(lambda: np.asarray(view.w.plot.data[1]).max() > 0, what="the ranking on the chart")


def test_next_worst_and_accept_walk_the_ranking(large):
    app, page, folder, expected = large
    view = app.review_panels()[0]
    worst = int(np.nanargmax(expected))
    page.get_by_role("button", name="Next worst frame").click()
    wait_until(lambda: _frame_shown(page, view, worst), what=f"the worst frame {worst}")
    # its bin carries the chart's maximum and the marker
    x, y, marker = (np.asarray(a) for a in view.w.plot.data)
    k = int(np.searchsorted(x, worst, side="right") - 1)
    assert y[k] == pytest.approx(1.0) and np.flatnonzero(np.isfinite(marker)).tolist() == [k]
    page.get_by_role("button", name="Accept").click()
    wait_until(
        lambda: journal(folder) and journal(folder)[-1]["command"].get("frame") == worst,
        what="the accept journaled",
    )
    assert journal(folder)[-1]["command"] == {
        "frame": worst,
        "kind": "set_review",
        "status": "accepted",
    }
    rest = expected.copy()
    rest[max(worst - NEIGHBOUR_RADIUS, 0) : worst + NEIGHBOUR_RADIUS + 1] = np.nan
    second = int(np.nanargmax(rest))
    wait_until(lambda: _frame_shown(page, view, second), what=f"the next worst frame {second}")
