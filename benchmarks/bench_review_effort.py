"""The effort curve on finished bench sessions: simulated review rounds per ranking, error against
frames touched, and the headline (frames touched to reach mean <= 3 mm with at most 1 % of frames
with a joint > 20 mm) per sequence and ranking.

Input: the first-pass sessions ``handanno bench --work-dir W`` keeps (``W/<dataset>/<strategy>-
<fraction>``); each ranking runs :func:`handanno_core.review_loop.review_rounds` on its own copy
(:func:`handanno_core.review_loop.bench_review`), so the first pass is not recomputed and every
ranking starts from the same one. One JSON per run plus one PNG (:func:`handanno_core.review_loop.
plot_effort`, one panel pair per sequence).

    python benchmarks/bench_review_effort.py W/report-fpha-1/forest-0.05 ... --rounds 6 \\
        --budget 0.05 --json out.json
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

from handanno_core.review_loop import bench_review, effort_to_target, review_rounds
from handanno_core.session import Session


def plot_suite(out: dict, path: Path) -> None:
    """One panel per sequence: mean error (left axis) and share of bad frames (right axis) against
    frames touched (% of the sequence), solid = evidence ranking, dashed = uniform corrections."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = out["runs"]
    cols = min(4, len(runs))
    rows = (len(runs) + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(3.6 * cols, 3.0 * rows), dpi=110, squeeze=False)
    styles = {"evidence": "-", "score": "-.", "uniform": "--"}
    for ax, run in zip(axes.ravel(), runs, strict=False):
        ax2 = ax.twinx()
        for ranking, entries in run["review"].items():
            x = [100.0 * e["frames_touched"] / run["frames"] for e in entries]
            ls = styles.get(ranking, ":")
            ax.plot(
                x,
                [e["mean_mm"] for e in entries],
                "C0",
                ls=ls,
                marker="o",
                ms=2.5,
                label=f"mean, {ranking}",
            )
            ax2.plot(
                x,
                [100.0 * e["bad_share"] for e in entries],
                "C3",
                ls=ls,
                marker="s",
                ms=2.5,
                label=f"bad %, {ranking}",
            )
        ax.axhline(3.0, color="C0", lw=0.6, ls=":")
        ax2.axhline(1.0, color="C3", lw=0.6, ls=":")
        ax.set_title(run["sequence"], fontsize=9)
        ax.set_xlabel("frames touched (%)", fontsize=8)
        ax.set_ylabel("mean error (mm)", color="C0", fontsize=8)
        ax2.set_ylabel("frames > 20 mm (%)", color="C3", fontsize=8)
        ax.grid(alpha=0.3)
    for ax in axes.ravel()[len(runs) :]:
        ax.axis("off")
    axes.ravel()[0].legend(fontsize=6, loc="upper right")
    fig.suptitle("effort curve: solid = evidence ranking, dashed = uniform corrections", fontsize=9)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def resume(folder: Path, review: dict, args) -> dict:
    """Continue each ranking's review copy ``<folder>-review-<ranking>`` (left by
    :func:`bench_review`) for ``args.rounds`` more rounds; the entries appended, renumbered."""
    out = {}
    for ranking, entries in review.items():
        session = Session.open(folder.with_name(f"{folder.name}-review-{ranking}"))
        try:
            more = review_rounds(
                session,
                rounds=args.rounds,
                budget=args.budget,
                ranking=ranking,
                reference_clicks=entries[-1]["joints_clicked"],
                workers=args.workers,
                quiet=True,
            )
        finally:
            session.close()
        last = entries[-1]["round"]
        out[ranking] = entries + [dict(e, round=last + e["round"]) for e in more[1:]]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sessions", nargs="+", type=Path)
    ap.add_argument("--rankings", default="evidence,uniform")
    ap.add_argument("--rounds", type=int, default=6)
    ap.add_argument("--budget", type=float, default=0.05, help="frames per round (< 1: share)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--json", type=Path, required=True)
    ap.add_argument(
        "--resume",
        type=Path,
        help="a JSON of an earlier run: continue its review copies for --rounds more rounds",
    )
    args = ap.parse_args()
    earlier = {}
    if args.resume:
        earlier = {r["session"]: r for r in json.loads(args.resume.read_text())["runs"]}
    out = {
        "rounds": args.rounds,
        "budget": args.budget,
        "rankings": args.rankings.split(","),
        "runs": [],
    }
    args.json.parent.mkdir(parents=True, exist_ok=True)
    for folder in args.sessions:
        s = Session.open(folder)
        frames, refs = s.num_frames, len(s.reference_frames)
        s.close()
        t, load = time.perf_counter(), os.getloadavg()[0]
        if str(folder) in earlier:
            review = resume(folder, earlier[str(folder)]["review"], args)
        else:
            review = bench_review(
                folder,
                rankings=out["rankings"],
                rounds=args.rounds,
                budget=args.budget,
                workers=args.workers,
                quiet=True,
            )
        run = {
            "sequence": folder.parent.name,
            "session": str(folder),
            "frames": frames,
            "references": refs,
            "review": review,
            "effort_to_target": {k: effort_to_target(v) for k, v in review.items()},
            "seconds": round(time.perf_counter() - t, 1),
            "load_avg_1m": [round(load, 2), round(os.getloadavg()[0], 2)],
        }
        out["runs"].append(run)
        print(run["sequence"], run["effort_to_target"], run["seconds"], "s", flush=True)
        for k, v in review.items():
            print("  ", k, [(e["frames_touched"], e["mean_mm"], e["bad_share"]) for e in v])
        args.json.write_text(json.dumps(out, indent=1))
        plot_suite(out, args.json.with_suffix(".png"))


if __name__ == "__main__":
    main()
