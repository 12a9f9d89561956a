"""Edit -> updated 3D skeleton latency of the annotation app (issue 7: at most 100 ms on the demo).

Measured server-side, as the issue defines it: from ``session.execute`` of an edit (which
journals and fsyncs it) to the moment the browser's view object assigns the newly lifted joint
positions to its skeleton handle (``AnnotateView.last_skeleton_update``). A real headless Chromium
is connected so the view, its handles and the websocket traffic are the real ones.

Scenarios on reference frames of the demo session (synthetic sequence, simulated annotator):

* ``adjust_2d``: move one joint of a fully annotated frame by a few pixels (the live-editing case:
  the lift is warm-started from the frame's previous solution);
* ``adjust_3d``: move one joint in 3D (a handle drag released);
* ``tip_slips``: a visible fingertip's 2D point moved off the finger onto a surface 20-60 mm
  behind it (within 8 px), nudged, and put back (the lift's elastic case);
* ``first_joints``: place the 1st..3rd joint on a new frame (cold lift, mostly unconstrained).

Usage: ``.venv/bin/python benchmarks/bench_app_latency.py [--edits 30] [--frames 300]``.
Writes benchmarks/results/app_latency.json.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import socket
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from app.ui.server import serve  # noqa: E402
from handanno_core.session import SetFrameAnnotation, SetJoint2D, SetJoint3D  # noqa: E402

TIPS = (4, 8, 12, 16, 20)  # MSRA21 fingertips (the demo's skeleton)


def slip_target(depth: np.ndarray, uv: np.ndarray, radius_px: int = 8) -> np.ndarray | None:
    """The pixel within ``radius_px`` of ``uv`` (at least 3 px away) whose valid depth lies 20-60 mm
    behind the surface at ``uv``, farthest such; None if there is none."""
    h, w = depth.shape
    u0, v0 = np.rint(uv).astype(int)
    r = np.arange(-radius_px, radius_px + 1)
    du, dv = np.meshgrid(r, r)
    uu, vv = u0 + du.ravel(), v0 + dv.ravel()
    inside = (uu >= 0) & (uu < w) & (vv >= 0) & (vv < h) & (np.hypot(du, dv).ravel() >= 3)
    uu, vv = uu[inside], vv[inside]
    here = depth[np.clip(v0, 0, h - 1), np.clip(u0, 0, w - 1)]
    if not here > 0:
        return None
    behind = depth[vv, uu].astype(np.float64) - here
    ok = (depth[vv, uu] > 0) & (behind > 20) & (behind < 60)
    if not ok.any():
        return None
    k = np.flatnonzero(ok)[np.argmax(behind[ok])]
    return np.array([uu[k], vv[k]], dtype=np.float64)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def stats(ms: list[float]) -> dict:
    a = np.asarray(ms)
    return {
        "n": len(a),
        "median_ms": round(float(np.median(a)), 1),
        "p90_ms": round(float(np.percentile(a, 90)), 1),
        "max_ms": round(float(a.max()), 1),
        "within_100ms": round(float(np.mean(a <= 100.0)), 3),
    }


def wait_for(pred, timeout=60.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        v = pred()
        if v:
            return v
        time.sleep(0.0005)
    raise TimeoutError("timed out")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--edits", type=int, default=30, help="edits per scenario")
    ap.add_argument("--frames", type=int, default=300, help="frames of the demo sequence")
    ap.add_argument(
        "--cache", type=Path, default=None, help="sessions dir to keep the demo session in"
    )
    ap.add_argument(
        "--out", type=Path, default=REPO / "benchmarks" / "results" / "app_latency.json"
    )
    args = ap.parse_args()

    from playwright.sync_api import sync_playwright

    from handanno_core.pipeline import ensure_demo_session
    from handanno_core.synth import simulate_annotation

    tmp = Path(tempfile.mkdtemp(prefix="bench-app-"))
    t0 = time.perf_counter()
    if args.cache is not None:  # reuse a demo made before (its edits are reset by copying)
        made = ensure_demo_session(args.cache, frames=args.frames, quiet=True)
        folder = tmp / "demo"
        shutil.copytree(made, folder)
        (folder / "journal.jsonl").unlink(missing_ok=True)
    else:
        folder = ensure_demo_session(tmp, frames=args.frames, quiet=True)
    setup_s = time.perf_counter() - t0
    load_start = os.getloadavg()[0]
    app = serve(folder, port=free_port(), block=False)
    session = app.session
    seq = session.open_sequence()
    gt = seq.ground_truth.joints_mm
    refs = [int(f) for f in session.reference_frames]
    rng = np.random.default_rng(0)
    results: dict[str, list[float]] = {
        "adjust_2d": [],
        "adjust_3d": [],
        "tip_slips": [],
        "first_joints": [],
    }
    breakdown: dict[str, list[float]] = {
        "execute_ms": [],
        "lift_ms": [],
        "app_overhead_ms": [],
        "edit_drawn_ms": [],
    }
    failures: list[str] = []
    needed_slack = dict.fromkeys(results, 0)  # lifts that could not meet a depth interval
    chromium = shutil.which("chromium")
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(
                executable_path=chromium,
                headless=True,
                args=[
                    "--use-angle=swiftshader",
                    "--enable-unsafe-swiftshader",
                    "--no-sandbox",
                    "--disable-gpu",
                ],
            )
            page = browser.new_page(viewport={"width": 1280, "height": 720})
            page.goto(app.url)
            view = wait_for(lambda: (app.annotate_panels() or [None])[0])

            def measure(command, scenario: str) -> None:
                start = time.perf_counter()
                entry = session.execute(command, client="bench")
                executed = time.perf_counter()
                lifted = wait_for(
                    lambda: (
                        (o := app.worker.latest.get(command.frame)) is not None
                        and o.journal_seq >= entry.seq
                        and o
                    )
                )
                if lifted.joints_mm is None:
                    failures.append(f"{scenario} frame {command.frame}: {lifted.error}")
                    return
                upd = wait_for(
                    lambda: (
                        view.last_skeleton_update
                        if view.last_skeleton_update and view.last_skeleton_update[0] >= entry.seq
                        else None
                    )
                )
                results[scenario].append(1000 * (upd[1] - start))
                needed_slack[scenario] += int(lifted.needed_slack)
                breakdown["execute_ms"].append(1000 * (executed - start))
                breakdown["lift_ms"].append(1000 * lifted.duration_s)
                breakdown["app_overhead_ms"].append(
                    1000 * (upd[1] - start) - 1000 * lifted.duration_s
                )
                drawn = view.last_edit_drawn
                if drawn is not None and drawn[0] >= entry.seq:
                    breakdown["edit_drawn_ms"].append(1000 * (drawn[1] - start))

            # Fully annotated frames: simulated annotator on the first references, then live edits.
            for frame in refs[:3]:
                view.go_to_index(view.state.frames.index(frame))
                view.flush()
                ann = simulate_annotation(
                    gt[frame], seq.depth(frame), session.camera, session.skeleton
                )
                entry = session.execute(
                    SetFrameAnnotation(frame=frame, annotation=ann.to_json()), client="bench"
                )
                wait_for(
                    lambda e=entry: (
                        view.last_skeleton_update and view.last_skeleton_update[0] >= e.seq
                    )
                )
                for _ in range(args.edits // 3):
                    j = int(rng.integers(1, session.skeleton.num_joints))
                    uv = ann.uv_px[j] + rng.uniform(-3, 3, 2)
                    measure(
                        SetJoint2D(frame=frame, joint=j, uv_px=(float(uv[0]), float(uv[1]))),
                        "adjust_2d",
                    )
                    time.sleep(0.05)
                    xyz = view._lifted.joints_mm[j] + rng.uniform(-4, 4, 3)
                    measure(
                        SetJoint3D(frame=frame, joint=j, xyz_mm=tuple(float(x) for x in xyz)),
                        "adjust_3d",
                    )
                    time.sleep(0.05)
                # A fingertip click that slips off the finger onto a surface behind it (palm,
                # another finger), nudged, and put back: the depth interval there is one no pose
                # can meet, the lift's elastic case.
                depth = seq.depth(frame)
                for t in TIPS:
                    slipped = slip_target(depth, ann.uv_px[t]) if ann.visible[t] else None
                    if slipped is None:
                        continue
                    for uv in (slipped, slipped + rng.uniform(-1, 1, 2), slipped, ann.uv_px[t]):
                        measure(
                            SetJoint2D(frame=frame, joint=t, uv_px=(float(uv[0]), float(uv[1]))),
                            "tip_slips",
                        )
                        time.sleep(0.05)
            # New frames: the first three joints.
            for frame in refs[3 : 3 + max(1, args.edits // 3)]:
                view.go_to_index(view.state.frames.index(frame))
                view.flush()
                ann = simulate_annotation(
                    gt[frame], seq.depth(frame), session.camera, session.skeleton
                )
                for j in range(3):
                    measure(
                        SetJoint2D(
                            frame=frame, joint=j, uv_px=tuple(float(x) for x in ann.uv_px[j])
                        ),
                        "first_joints",
                    )
                    time.sleep(0.05)
            browser.close()
    finally:
        app.stop()
        shutil.rmtree(tmp, ignore_errors=True)

    report = {
        "definition": "session.execute of an edit -> view assigns the lifted skeleton positions (server-side)",
        "target_ms": 100,
        "scenarios": {k: stats(v) for k, v in results.items() if v},
        "breakdown": {k: stats(v) for k, v in breakdown.items() if v},
        "breakdown_meaning": {
            "execute_ms": "session.execute: validate + journal append + fsync + apply",
            "lift_ms": "lift_frame in the worker (handanno_core.lift)",
            "app_overhead_ms": "total minus lift: queueing, dispatch, handle assignment",
            "edit_drawn_ms": "execute -> the edited joint drawn at its new place (before the lift)",
        },
        "lift_failures": failures,
        "lifts_needing_elastic_slack": needed_slack,
        "conditions": {
            "session": f"demo (synthetic, {args.frames} frames, {len(refs)} references, 320x240)",
            "browser": "headless Chromium (SwiftShader) connected to the server",
            "cpu_count": os.cpu_count(),
            "machine": platform.platform(),
            "python": platform.python_version(),
            "edits_per_scenario": args.edits,
            "load_average_1min": [round(load_start, 2), round(os.getloadavg()[0], 2)],
            "setup_s": round(setup_s, 1),
        },
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2))
    for name, s in report["scenarios"].items():
        print(
            f"{name:13s} median {s['median_ms']:7.1f} ms  p90 {s['p90_ms']:7.1f} ms  max {s['max_ms']:7.1f} ms  "
            f"<=100 ms: {100 * s['within_100ms']:.0f}%  (n={s['n']})"
        )
    for name, s in report["breakdown"].items():
        print(f"  {name:15s} median {s['median_ms']:7.1f} ms  p90 {s['p90_ms']:7.1f} ms")
    for f in failures:
        print("lift failed:", f)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
