"""Clicks per reference with pre-filled references, and what the accepted guesses cost in lift error.

For each finished bench session given (``handanno bench --work-dir``), a fresh session with the
same dataset, selection and cached crops is annotated by the simulated annotator once per mode:
every joint clicked (``annotate_from_gt``), or pre-filled (:func:`handanno_core.review_loop.
annotate_prefilled`: one guess moved at a time, the guesses refitted after each click as the
app's live lift does, guesses within 4 px of the truth accepted). Each is lifted (bone lengths
estimated as the pipeline does) and compared with ground truth.

    python benchmarks/bench_prefill.py SESSION [SESSION ...] --json out.json
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

from handanno_core import pipeline
from handanno_core.bench import run_session
from handanno_core.evaluate import error_summary
from handanno_core.guesses import GuessWeights
from handanno_core.review_loop import annotate_prefilled
from handanno_core.session import Session


def prefill_options(mode: str, click_px: float) -> dict:
    """:func:`annotate_prefilled` keyword arguments of a pre-filled ``mode`` (see ``--modes``)."""
    parts = mode.split("-")
    if parts[0] != "interactive":
        raise ValueError(f"unknown mode {mode!r}")
    px = [float(p[2:]) for p in parts if p.startswith("px")]
    uvw = [float(p[3:]) for p in parts if p.startswith("uvw")]
    posew = [float(p[5:]) for p in parts if p.startswith("posew")]
    weights = GuessWeights()
    return {
        "click_px": px[0] if px else click_px,
        "hand_model": "model" in parts,
        "model_refit": "refit" in parts,
        "guess_weights": GuessWeights(
            uv=uvw[0] if uvw else weights.uv, pose=posew[0] if posew else weights.pose
        ),
    }


def fresh_copy(src: Session, folder: Path) -> Session:
    """A fresh session on ``src``'s dataset with its settings (the crops' cube, grown per
    sequence), crop cache and selection, and no annotation (:func:`handanno_core.bench.run_session`)."""
    s = run_session(src, folder)
    sel = src.model.selection.model_dump()
    sel["parent"] = list(src.model.selection.parent)
    s.set_selection(sel)
    return s


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sessions", nargs="+", type=Path)
    ap.add_argument("--work", type=Path, default=Path("/tmp/handanno-bench-prefill"))
    ap.add_argument("--click-px", type=float, default=4.0, help="joints farther off are moved")
    ap.add_argument("--noise-px", type=float, default=0.0, help="2D noise of a click (std, px)")
    ap.add_argument(
        "--modes",
        default="all_clicks,interactive-model-refit",
        help="comma-separated: all_clicks, interactive (one guess at a time, refit after each "
        "click, as in the app, the bones estimated from the references so far; -model: each "
        "pre-fill fitted with the hand model personalized from the references so far; -refit: "
        "each refit also fits the unplaced joints with that hand model (interactive-model-refit: "
        "the default of annotate_prefilled and of handanno bench --prefill), -uvwX / -posewX its "
        "2D / pose weights; -pxN: guesses more than N px off are moved instead of --click-px)",
    )
    ap.add_argument("--json", type=Path, required=True)
    args = ap.parse_args()
    rows = []
    for folder in args.sessions:
        src = Session.open(folder)
        gt = src.open_sequence().ground_truth.joints_mm
        row: dict = {
            "session": str(folder),
            "references": int(len(src.reference_frames)),
            "click_px": args.click_px,
            "load_avg_1m_before": round(os.getloadavg()[0], 2),
        }
        for mode in args.modes.split(","):
            s = fresh_copy(src, args.work / f"{folder.parent.name}-{folder.name}-{mode}")
            t = time.perf_counter()
            if mode.startswith("interactive"):
                refit_s: list[float] = []
                info = annotate_prefilled(
                    s,
                    noise_px=args.noise_px,
                    refit_s=refit_s,
                    quiet=True,
                    **prefill_options(mode, args.click_px),
                )
                row[f"{mode}_detail"] = {
                    str(f): {
                        "clicks": info["clicks"][f],
                        "click_order": info["click_order"].get(f, []),
                        "guess_off_px": info["guess_off_px"].get(f),
                        "guess_mm": None
                        if f not in info["guess_mm"]
                        else np.round(info["guess_mm"][f], 2).tolist(),
                        "gap": info["gap"].get(f),
                    }
                    for f in info["order"]
                }
                if refit_s:
                    ms = np.asarray(refit_s) * 1000.0
                    row[f"{mode}_refit_ms"] = {
                        "mean": round(float(ms.mean()), 1),
                        "p90": round(float(np.percentile(ms, 90)), 1),
                        "max": round(float(ms.max()), 1),
                        "count": int(ms.size),
                    }
                row[f"{mode}_clicks_per_reference"] = round(info["clicks_per_reference"], 3)
                row[f"{mode}_clicks"] = [int(c) for c in info["clicks"].values()]
            else:
                pipeline.annotate_from_gt(s, noise_px=args.noise_px, quiet=True)
            row[f"{mode}_annotate_s"] = round(time.perf_counter() - t, 2)
            pipeline.lift(s, quiet=True)
            refs = s.reference_frames
            lifted = s.load_results()["lifted_mm"]
            e = error_summary(lifted, gt, frames=refs)
            row[f"{mode}_lift_mm"] = {k: round(float(e[k]), 3) for k in ("mean_mm", "max_mm")}
            s.close()
        src.close()
        rows.append(row)
        print(
            json.dumps({k: v for k, v in row.items() if not k.endswith(("clicks", "detail"))}),
            flush=True,
        )
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps({"rows": rows}, indent=1))


if __name__ == "__main__":
    main()
