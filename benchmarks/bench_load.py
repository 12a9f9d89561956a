"""Load test of the app: four browser clients (Playwright, headless Chromium) editing the demo session.

Usage: ``.venv/bin/python benchmarks/bench_load.py [--seconds 60] [--clients 4] [--sessions-dir DIR]``

The server runs in this process on a copy-free demo session made in ``--sessions-dir`` (default: a
temporary folder, so the repository's ``sessions/demo`` is left alone). Two pages edit in the
Annotate tab (toggle the selected joint's visibility on their reference frame, moving to the next
reference every few edits; pages start on the same frame, so their edits collide) and two in the
Review tab (Accept / Flag / Clear the shown frame, stepping frames). Every edit is a click on a panel
button; it counts as *acknowledged* when the page shows the "saved ... #seq" text for a new journal
sequence number, and the click-to-acknowledgement time is the ack latency. At the end every
acknowledged sequence number is looked up in ``journal.jsonl`` (a lost edit is one acknowledged but
missing there), and the session is reopened from disk to check the last values.

Writes benchmarks/results/load.json: edits/s, p50/p95 ack latency (page round trip) and the server
side ``Session.execute`` time, errors, lost edits.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import re
import shutil
import socket
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
#: small pages: with software WebGL the canvas fill rate is what loads the CPU
VIEWPORT = {"width": 960, "height": 600}
sys.path.insert(0, str(ROOT))

CHROMIUM_ARGS = [
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--no-first-run",
    # four pages at once: keep the background ones rendering (else clicks wait for animation frames)
    "--disable-background-timer-throttling",
    "--disable-renderer-backgrounding",
    "--disable-backgrounding-occluded-windows",
]
# The seq number of this page's last acknowledged edit, from the visible panel text.
ACK_JS = r"""() => {
  const t = document.body.innerText;
  let best = -1;
  for (const m of t.matchAll(/saved \d\d:\d\d:\d\d \((?:edit|undo|redo) #(\d+)\)|review saved \d\d:\d\d:\d\d \(#(\d+)\)/g)) {
    best = Math.max(best, parseInt(m[1] || m[2]));
  }
  return best;
}"""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


async def wait_ack(page, prev: int, timeout_s: float = 15.0) -> int:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        seq = await page.evaluate(ACK_JS)
        if seq > prev:
            return seq
        await asyncio.sleep(0.01)
    raise TimeoutError(f"no acknowledgement after {timeout_s:.0f} s")


async def client_loop(index: int, browser, url: str, seconds: float, stats: dict) -> None:
    context = await browser.new_context(viewport=VIEWPORT)
    page = await context.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(f"page error: {exc}"))
    await page.goto(url)
    await page.wait_for_function(
        "() => !document.body.innerText.includes('Connecting...') && window.__viserMutable"
        " && window.__viserMutable.nodeRefFromName['/annotate/joints'] !== undefined",
        timeout=120_000,
    )
    mode = "annotate" if index % 2 == 0 else "review"
    if mode == "review":
        await page.get_by_role("tab", name="Review").click(force=True, timeout=120_000)
        await page.get_by_role("button", name="Accept").wait_for(timeout=60_000)
    acks: list[int] = []  # every acknowledged seq (warm-up included)
    latencies: list[float] = []  # click start -> ack shown
    round_trips: list[float] = []  # click delivered -> ack shown
    timed = 0
    last = -1
    n = 0

    def target():
        if mode == "annotate":
            return page.get_by_role("button", name=re.compile(r"^Visibility: "))
        return page.get_by_role("button", name=("Accept", "Flag", "Clear")[n % 3], exact=True)

    # Warm-up (not timed): the first click waits for the page to finish its first scene.
    await target().click(force=True, timeout=120_000)
    last = await wait_ack(page, last, 120)
    acks.append(last)
    stats["ready"] += 1
    while stats["ready"] < stats["clients"]:
        await asyncio.sleep(0.05)
    t_end = time.monotonic() + seconds
    while time.monotonic() < t_end:
        n += 1
        try:
            if mode == "annotate" and n % 6 == 0:
                await page.get_by_role("button", name="Next (N) ▶").click(force=True)
            elif mode == "review" and n % 5 == 0:
                await page.get_by_role("button", name="▶", exact=True).click(force=True)
            t0 = time.perf_counter()
            await target().click(timeout=20_000, force=True)
            t1 = time.perf_counter()
            last = await wait_ack(page, last)
            t2 = time.perf_counter()
            latencies.append(t2 - t0)
            round_trips.append(t2 - t1)
            acks.append(last)
            timed += 1
        except Exception as exc:  # counted, the loop goes on
            errors.append(f"{type(exc).__name__}: {str(exc).splitlines()[0][:200]}")
            last = max(last, await page.evaluate(ACK_JS))
    stats["per_client"].append(
        {
            "client": index,
            "mode": mode,
            "acknowledged": len(acks),
            "timed": timed,
            "errors": errors,
            "acks": acks,
            "latencies": latencies,
            "round_trips": round_trips,
        }
    )
    await context.close()


async def drive(url: str, clients: int, seconds: float) -> dict:
    from playwright.async_api import async_playwright

    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe is None:
        raise SystemExit("bench_load: no chromium on PATH (apt install chromium)")
    stats: dict = {"ready": 0, "clients": clients, "per_client": []}
    async with async_playwright() as p:
        browser = await p.chromium.launch(executable_path=exe, headless=True, args=CHROMIUM_ARGS)
        try:
            await asyncio.gather(
                *(client_loop(i, browser, url, seconds, stats) for i in range(clients))
            )
        finally:
            await browser.close()
    return stats


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--clients", type=int, default=4)
    parser.add_argument("--sessions-dir", type=Path, default=None)
    parser.add_argument("--json", type=Path, default=ROOT / "benchmarks" / "results" / "load.json")
    args = parser.parse_args(argv)

    from app.ui.server import serve
    from handanno_core.pipeline import ensure_demo_session
    from handanno_core.session import JOURNAL_FILE, Session

    tmp = None
    if args.sessions_dir is None:
        tmp = tempfile.mkdtemp(prefix="handanno-load-")
        args.sessions_dir = Path(tmp)
    t0 = time.perf_counter()
    folder = ensure_demo_session(args.sessions_dir, quiet=True)
    print(f"demo session ready in {time.perf_counter() - t0:.1f} s: {folder}")
    journal_path = folder / JOURNAL_FILE
    start_lines = len(journal_path.read_text().splitlines()) if journal_path.exists() else 0

    app = serve(folder, port=free_port(), block=False)
    execute_s: list[float] = []
    original = app.session.execute

    def timed_execute(*a, **kw):
        t = time.perf_counter()
        try:
            return original(*a, **kw)
        finally:
            execute_s.append(time.perf_counter() - t)

    app.session.execute = timed_execute  # type: ignore[method-assign]
    try:
        t_run = time.perf_counter()
        stats = asyncio.run(drive(app.url, args.clients, args.seconds))
        wall = time.perf_counter() - t_run
        app.worker.wait_idle(30)
    finally:
        app.stop()

    text = journal_path.read_text() if journal_path.exists() else ""
    lines = [json.loads(x) for x in text.splitlines()[start_lines:] if x.strip()]
    journal_seqs = {e["seq"] for e in lines}
    by_client = {}
    for e in lines:
        by_client[e["client"]] = by_client.get(e["client"], 0) + 1
    acked = [s for c in stats["per_client"] for s in c["acks"]]
    lost = sorted(set(acked) - journal_seqs)
    latencies = np.array([x for c in stats["per_client"] for x in c["latencies"]]) * 1000.0
    round_trips = np.array([x for c in stats["per_client"] for x in c["round_trips"]]) * 1000.0
    timed = sum(c["timed"] for c in stats["per_client"])
    errors = [e for c in stats["per_client"] for e in c["errors"]]
    reopened = Session.open(folder)  # replays the journal: must not fail
    reopened_seq = reopened.model.journal_seq
    reopened.close()
    edits = len(acked)
    result = {
        "clients": args.clients,
        "seconds": args.seconds,
        "wall_s": round(wall, 1),
        "acknowledged_edits": edits,
        "journal_entries": len(lines),
        "journal_entries_by_client": by_client,
        "lost_edits": len(lost),
        "unacknowledged_journal_entries": len(journal_seqs - set(acked)),
        "timed_edits": timed,
        "edits_per_s": round(timed / args.seconds, 2),
        "ack_latency_ms": {
            "p50": round(float(np.percentile(round_trips, 50)), 1) if timed else None,
            "p95": round(float(np.percentile(round_trips, 95)), 1) if timed else None,
            "max": round(float(round_trips.max()), 1) if timed else None,
            "what": "click delivered to the page -> the page shows 'saved #seq' (websocket, server, back)",
        },
        "click_to_ack_ms": {
            "p50": round(float(np.percentile(latencies, 50)), 1) if timed else None,
            "p95": round(float(np.percentile(latencies, 95)), 1) if timed else None,
            "what": "including Playwright's input dispatch (slow on this loaded VM)",
        },
        "server_execute_ms": {
            "p50": round(float(np.percentile(execute_s, 50)) * 1000, 2) if execute_s else None,
            "p95": round(float(np.percentile(execute_s, 95)) * 1000, 2) if execute_s else None,
            "what": "Session.execute: validate, journal append + fsync, apply, notify views",
        },
        "errors": len(errors),
        "error_samples": errors[:10],
        "per_client": [
            {k: c[k] for k in ("client", "mode", "acknowledged", "timed")}
            | {"errors": len(c["errors"])}
            for c in sorted(stats["per_client"], key=lambda c: c["client"])
        ],
        "reopened_journal_seq": reopened_seq,
        "conditions": f"one headless Chromium (SwiftShader), {args.clients} pages of {VIEWPORT['width']}x{VIEWPORT['height']}, "
        "server in the same process, "
        "2-core VM shared with other jobs",
    }
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps({k: v for k, v in result.items() if k != "error_samples"}, indent=1))
    if tmp is not None:
        shutil.rmtree(tmp, ignore_errors=True)
    return 0 if not lost and not errors else 1


if __name__ == "__main__":
    sys.exit(main())
