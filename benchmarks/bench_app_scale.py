"""The app on a large session (issue 19): open time and server-side time per review action.

Serves a session in the real server (``app.ui.server.serve``) with a headless Chromium connected,
then drives the Review tab through its panel methods, each timed on the server from the call to
the end of the redraw it posted on the client's UI thread (``ClientUI.flush``: the frame's depth
read, its cloud and skeleton assigned to the scene handles, the panel text and the priority
chart updated). Actions:

* ``timeline``: move the review timeline to a random frame (what the slider's callback does);
* ``step``: one frame forward (the slider's arrow, playback);
* ``next_worst``: "Next worst frame" (the walk over the background ranking);
* ``accept``: "Accept" (journals and fsyncs the status, then goes on to the next worst frame);
* ``annotate_next``: the Annotate tab's next reference frame (its frame list).

Reported per action: median, p95 and max (ms). Also: the open time (``serve`` called -> session
opened, journal replayed, app context ready), the first page's UI built (browser connected ->
its panels constructed and first scene drawn), and when the first background ranking of every
frame was ready (seconds after ``serve`` was called) and how long one ranking takes.

The session is either an existing one (``--session DIR``: a light copy is served, so the
original is never written: its ``session.json``, ``journal.jsonl``, ``results.npz`` and
``crops_meta.npz`` copied, ``crops.npy`` linked) or a tiled one (``--copies C``: C copies of a
``--base-frames``-frame synthetic sequence, ``tests/large_session.py``).

    nice .venv/bin/python benchmarks/bench_app_scale.py --session /path/to/session [--actions 40]
        [--json benchmarks/results/app_scale.json]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tests"))
sys.path.insert(0, str(REPO / "tests" / "e2e"))

from viser_helpers import CHROMIUM_ARGS, free_port  # noqa: E402  (the e2e tests' port finder)

from handanno_core.bench import machine_description  # noqa: E402

LIGHT_COPY = ("session.json", "journal.jsonl", "results.npz", "crops_meta.npz")


def light_copy(src: Path, dst: Path) -> Path:
    """A copy of session ``src`` that can be written without touching ``src``: the small files
    copied, the crop cache (read-only for the app) linked."""
    dst.mkdir(parents=True)
    for name in LIGHT_COPY:
        if (src / name).exists():
            shutil.copy2(src / name, dst / name)
    if (src / "crops.npy").exists():
        os.symlink((src / "crops.npy").resolve(), dst / "crops.npy")
    return dst


def stats(ms: list[float]) -> dict:
    a = np.asarray(ms)
    return {
        "n": len(a),
        "median_ms": round(float(np.median(a)), 1),
        "p95_ms": round(float(np.percentile(a, 95)), 1),
        "max_ms": round(float(a.max()), 1),
        "within_200ms": round(float(np.mean(a <= 200.0)), 3),
    }


def wait_for(pred, timeout=300.0, what="condition"):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        v = pred()
        if v:
            return v
        time.sleep(0.002)
    raise TimeoutError(f"timed out waiting for {what}")


def prepare(args: argparse.Namespace, tmp: Path) -> tuple[Path, str]:
    """The folder to serve (a light copy) and a description of the session."""
    if args.session is not None:
        return light_copy(args.session.resolve(), tmp / "session"), str(args.session)
    from large_session import build_large_session

    from handanno_core.synth import generate_sequence

    root = args.keep or tmp
    base = root / "base"
    if not (base / "joint.txt").exists():
        generate_sequence(base, frames=args.base_frames, seed=0, progress=False, workers=1)
    built = root / "tiled"
    if not (built / "session.json").exists():
        build_large_session(built, base, args.copies)
    source = f"tiled: {args.copies} x {args.base_frames}-frame synthetic sequence"
    return light_copy(built, tmp / "session"), source


def drive(app, actions: int, t_serve: float) -> dict:
    """Connect a headless Chromium, wait for the first ranking, time every action."""
    from playwright.sync_api import sync_playwright

    rng = np.random.default_rng(0)
    n = app.session.num_frames
    times: dict[str, list[float]] = {
        "timeline": [], "step": [], "next_worst": [], "accept": [], "annotate_next": [],
    }  # fmt: skip
    with sync_playwright() as p:
        browser = p.chromium.launch(
            executable_path=shutil.which("chromium"), headless=True, args=CHROMIUM_ARGS
        )
        page = browser.new_page(viewport={"width": 1280, "height": 720})
        t_page = time.perf_counter()
        page.goto(app.url)
        ui = wait_for(lambda: (app.clients() or [None])[0], what="the page's UI")
        ui.flush(120)
        ui_s = time.perf_counter() - t_page
        panel = ui.review

        def timed(name: str, action) -> None:
            start = time.perf_counter()
            action()
            ui.flush(120)
            times[name].append(1000 * (time.perf_counter() - start))

        for _ in range(actions):
            timed("annotate_next", ui.annotate.next_frame)
        ui.show("review")
        ui.flush(120)
        app.ctx.live.ranking(wait_s=None)
        ranked_s = time.perf_counter() - t_serve
        for _ in range(actions):
            f = int(rng.integers(0, n))
            timed("timeline", lambda f=f: panel.show_frame(f))
            timed("step", lambda: panel.step_frame(+1))
        for _ in range(actions):
            timed("next_worst", panel.go_worst)
        for _ in range(actions):
            timed("accept", panel.accept)
        assert panel.frame == panel.state.walked[-1], "accept did not go on to the next worst"
        browser.close()
    return {
        "first_page_ui_s": round(ui_s, 2),
        "first_ranking_ready_s": round(ranked_s, 1),
        "one_ranking_s": round(app.ctx.live.rank_seconds, 1),
        "actions": {k: stats(v) for k, v in times.items() if v},
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--session", type=Path, help="an existing session (served from a light copy)")
    ap.add_argument("--copies", type=int, default=765, help="tiled session: copies of the base")
    ap.add_argument("--base-frames", type=int, default=100, help="tiled session: base frames")
    ap.add_argument("--actions", type=int, default=40, help="repetitions of each action")
    ap.add_argument("--keep", type=Path, help="build/keep the tiled session under this folder")
    ap.add_argument("--json", type=Path, default=REPO / "benchmarks/results/app_scale.json")
    args = ap.parse_args()

    from app.ui.server import serve

    tmp = Path(tempfile.mkdtemp(prefix="bench-app-scale-"))
    t0 = time.perf_counter()
    folder, source = prepare(args, tmp)
    setup_s = time.perf_counter() - t0
    load = [round(os.getloadavg()[0], 2)]
    t_serve = time.perf_counter()
    app = serve(folder, port=free_port(), block=False)
    open_s = time.perf_counter() - t_serve
    n = app.session.num_frames
    try:
        measured = drive(app, args.actions, t_serve)
    finally:
        app.stop()
        shutil.rmtree(tmp, ignore_errors=True)
    load.append(round(os.getloadavg()[0], 2))
    report = {
        "definition": (
            "server-side: panel action called -> the redraw it posted on the client's UI thread "
            "done (ClientUI.flush); a headless Chromium is connected"
        ),
        "session": source,
        "frames": n,
        "open_s": round(open_s, 2),
        "open_meaning": "serve() called -> session opened, journal replayed, app context ready",
        "first_page_ui_meaning": "page.goto -> the page's panels built and first scene drawn",
        **measured,
        "conditions": {
            "machine": machine_description(),
            "load_average_1min_start_end": load,
            "setup_s": round(setup_s, 1),
            "actions_each": args.actions,
        },
    }
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(report, indent=2))
    print(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
