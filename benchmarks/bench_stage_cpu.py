"""CPU seconds of propagation and refinement (hand model on) on a lifted session, optionally profiled.

Usage::

    .venv/bin/python benchmarks/bench_stage_cpu.py SESSION [SESSION ...] [--model on|off]
        [--profile OUT_PREFIX] [--frames A:B] [--json OUT]

``SESSION``: a lifted session folder (e.g. ``handanno bench ... --work-dir W`` keeps
``W/forest-0.05``). The session is copied to a temporary folder (the original is not written),
then ``pipeline.propagate`` (one worker) and ``pipeline.refine`` (one system) run on the copy.
Per stage: CPU seconds (user + system of this process, ``resource.getrusage``: the machine is
shared, so wall time is noisy), wall seconds, the load average before the stage, and the final
errors against the ground truth. ``--profile P`` writes pyinstrument HTML/text profiles
``P-propagate.*`` and ``P-refine.*`` (``pip install pyinstrument``, a dev dependency).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import tempfile
import time
from pathlib import Path

from handanno_core import pipeline
from handanno_core.bench import copy_session, stage_errors
from handanno_core.session import Session


def _cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def _stage(name: str, fn, profile: str | None) -> dict:
    load = os.getloadavg()[0]
    profiler = None
    if profile:
        from pyinstrument import Profiler

        profiler = Profiler(interval=0.005)
        profiler.start()
    c0, t0 = _cpu(), time.perf_counter()
    fn()
    out = {
        "cpu_s": round(_cpu() - c0, 2),
        "wall_s": round(time.perf_counter() - t0, 2),
        "load_before": round(load, 2),
    }
    if profiler is not None:
        profiler.stop()
        Path(f"{profile}-{name}.txt").write_text(
            profiler.output_text(unicode=False, show_all=False)
        )
        Path(f"{profile}-{name}.html").write_text(profiler.output_html())
    return out


def run_one(folder: Path, use_model: bool, profile: str | None) -> dict:
    tmp = Path(tempfile.mkdtemp(prefix="bench-stage-cpu-"))
    try:
        work = tmp / "s"
        copy_session(folder, work)
        session = Session.open(work)
        gt = session.open_sequence().ground_truth.joints_mm
        row = {"session": str(folder), "frames": session.num_frames, "model": use_model}
        row["propagate"] = _stage(
            "propagate",
            lambda: pipeline.propagate(session, workers=1, quiet=True, use_model=use_model),
            profile,
        )
        row["refine"] = _stage(
            "refine", lambda: pipeline.refine(session, quiet=True, use_model=use_model), profile
        )
        errs = stage_errors(session.load_results(), gt, session.reference_frames)
        row["init"], row["final"] = errs["init"], errs["final"]
        session.close()
        return row
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sessions", nargs="+")
    ap.add_argument("--model", default="on", choices=["on", "off"])
    ap.add_argument("--profile", default=None, help="prefix of pyinstrument profiles")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    rows = []
    for i, s in enumerate(args.sessions):
        prof = None if args.profile is None else f"{args.profile}{i}"
        row = run_one(Path(s), args.model == "on", prof)
        rows.append(row)
        p, r = row["propagate"], row["refine"]
        print(
            f"{s}: {row['frames']} frames | propagate {p['cpu_s']:.1f} cpu-s ({p['wall_s']:.1f} s, "
            f"load {p['load_before']:.1f}) | refine {r['cpu_s']:.1f} cpu-s ({r['wall_s']:.1f} s, "
            f"load {r['load_before']:.1f}) | init {row['init']['mean_mm']:.3f} / "
            f"final {row['final']['mean_mm']:.3f} {row['final']['median_mm']:.3f} "
            f"{row['final']['max_mm']:.2f} mm",
            flush=True,
        )
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
