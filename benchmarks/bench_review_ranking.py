"""Choose the "evidence" review ranking's weights on a tune part; measure recall@10 % everywhere.

Input: finished bench sessions (``handanno bench --work-dir`` keeps them; each holds refined
results and the cached crops). For every session the evidence of :func:`handanno_core.review.
review_evidence` is computed for the non-reference frames; ground truth labels a frame bad when a
joint is more than ``--bad-mm`` off (evaluation and weight fitting only).

The weights: a logistic regression (non-negative weights, L2, on ``log1p(x / scale)`` with each
term's scale = its median over the tune frames) fitted on the ``--tune`` sessions only, with frames
bad at ``--fit-mm`` as the positive class (``--search``: coordinate ascent of the tune objective
instead, :func:`tune_objective` at ``--objective-mm``; ``--add-term NAME:SCALE``: the weights before
kept and one new term's weight chosen on a grid). ``--loso``: the same choice made without
each tune sequence (all its suite replicas) and scored on it. ``--smoothing``: also search temporal
smoothing and neighbour suppression (off otherwise: the committed ``review.SMOOTH`` /
``SUPPRESS_RADIUS``). ``--fixed``: report the committed ``review.EVIDENCE_WEIGHTS``. recall@10 %
(share of bad frames among the ranking's first 10 % of frames) at ``--bad-mm`` and 40 mm, and the
rank correlation with the frame error, are then reported per session for the app's ranking
until now (``score``), :data:`BEFORE_WEIGHTS`, the chosen weights and each term alone, with the
bad frames the chosen ranking finds and misses and how many of each are bad only in joints the
frame's depth does not show at their true position (:func:`missed_counts`). The
weights to paste into ``handanno_core/review.py`` are printed and written with the report.

    python benchmarks/bench_review_ranking.py --tune S0 S1 --report S2 S3 --loso \
        --objective-mm 10,15,20,30,40 --json out.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from handanno_core import review
from handanno_core.bench import shown_by_depth
from handanno_core.prefill import cached_crops
from handanno_core.session import Session


def load(folder: Path, bad_mm: float, cache: Path | None = None) -> dict:
    """One finished bench session: its evidence, the old ranking, ground-truth frame errors. With
    ``cache`` (a folder) the arrays are stored there and read back on the next run."""
    name = f"{folder.parent.parent.name}/{folder.parent.name}/{folder.name}"
    sequence = _sequence_name(folder)
    hit = None if cache is None else cache / (name.replace("/", "__") + ".npz")
    if hit is not None and hit.exists():
        with np.load(hit) as z:
            if "shown_err" in z.files:  # else a cache of an older version: computed again
                ev = {k[3:]: z[k] for k in z.files if k.startswith("ev_")}
                return {
                    "name": name,
                    "sequence": sequence,
                    "evidence": ev,
                    "score": z["score"],
                    "err": z["err"],
                    "shown_err": z["shown_err"],
                    "refs": z["refs"],
                    "n": int(z["n"]),
                    "breaks": list(z["breaks"]),
                }
    session = Session.open(folder)
    try:
        results = session.load_results()
        crop_data = cached_crops(session)
        sequence_data = session.open_sequence()
        gt = sequence_data.ground_truth.joints_mm
        final = np.asarray(results["final_mm"], dtype=np.float64)
        joint_err = np.linalg.norm(final - gt, axis=-1)
        err = joint_err.max(axis=1)
        shown = shown_by_depth(sequence_data, session.skeleton, gt, np.arange(len(gt)))
        shown_err = np.max(np.where(shown, np.nan_to_num(joint_err, nan=np.inf), 0.0), axis=1)
        ev = review.review_evidence(session, results, crop_data)
        score = review.rank_priority("score", session, results, crop_data)
        d = {
            "name": name,
            "sequence": sequence,
            "evidence": ev,
            "score": score,
            "err": err,
            "shown_err": shown_err,
            "refs": np.asarray(session.reference_frames, dtype=np.int64),
            "n": session.num_frames,
            "breaks": list(session.model.sequence_breaks),
        }
    finally:
        session.close()
    if hit is not None:
        hit.parent.mkdir(parents=True, exist_ok=True)
        np.savez(
            hit,
            score=d["score"],
            err=d["err"],
            shown_err=d["shown_err"],
            refs=d["refs"],
            n=d["n"],
            breaks=np.asarray(d["breaks"], dtype=np.int64),
            **{f"ev_{k}": v for k, v in ev.items()},
        )
    return d


def features(ev: dict, names: list[str], scales: dict[str, float]) -> np.ndarray:
    cols = []
    for k in names:
        t = np.log1p(np.maximum(np.asarray(ev[k], dtype=np.float64), 0.0) / scales[k])
        cols.append(np.where(np.isfinite(t), t, 0.0))
    return np.stack(cols, axis=1)


def fit_logistic(x: np.ndarray, y: np.ndarray, l2: float = 1e-2, iters: int = 4000) -> np.ndarray:
    """Non-negative weights ``(F,)`` and a bias (last) by projected gradient descent."""
    mu = x.mean(axis=0)
    sd = x.std(axis=0) + 1e-9
    z = (x - mu) / sd
    w = np.zeros(x.shape[1])
    b = 0.0
    pos = max(y.mean(), 1e-3)
    sw = np.where(y, 0.5 / pos, 0.5 / (1 - pos))  # balanced classes
    lr = 0.5
    for _ in range(iters):
        p = 1.0 / (1.0 + np.exp(-(z @ w + b)))
        g = sw * (p - y)
        w -= lr * (z.T @ g / len(y) + l2 * w)
        b -= lr * g.mean()
        w = np.maximum(w, 0.0)
    return w / sd  # weights on the raw (unstandardized) features; the bias does not rank


def ceiling(bad: np.ndarray, refs: np.ndarray, share: float = 0.10) -> float:
    """The best recall@10 % possible: 1, or (10 % of the frames) / (bad frames) when fewer."""
    b = bad.copy()
    b[refs] = False
    return min(1.0, round(share * len(bad)) / max(int(b.sum()), 1))


def missed_counts(
    priority: np.ndarray,
    err: np.ndarray,
    shown_err: np.ndarray,
    refs: np.ndarray,
    bad_mm: float,
    share: float = 0.10,
    **pick,
) -> dict:
    """Which bad frames (worst joint ``err`` (N,) mm over ``bad_mm``, references left out) the
    ranking's first ``share`` of frames (:func:`review.pick_frames` of ``priority`` (N,), keyword
    arguments ``pick``) finds and which it misses, and of each, how many are bad only in joints
    their frame's depth does not show (``shown_err`` (N,) mm: the largest error over the joints
    it shows at their true position; such a frame's error is invisible to any evidence from its
    own depth)."""
    err = np.asarray(err, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        bad = err > bad_mm
        hidden_only = bad & ~(np.asarray(shown_err, dtype=np.float64) > bad_mm)
    bad[refs] = False
    top = np.zeros(len(err), dtype=bool)
    top[review.pick_frames(priority, int(round(share * len(err))), exclude=refs, **pick)] = True
    return {
        "found": int((bad & top).sum()),
        "found_hidden_only": int((bad & top & hidden_only).sum()),
        "missed": int((bad & ~top).sum()),
        "missed_hidden_only": int((bad & ~top & hidden_only).sum()),
    }


def priority_of(d: dict, weights: dict, smooth: tuple[int, float]) -> np.ndarray:
    p = review.evidence_priority(d["evidence"], weights)
    return review.smooth_in_time(p, smooth[0], smooth[1], d["breaks"])


#: the thresholds (mm) of :func:`tune_objective` (``--objective-mm``); empty: ``bad_mm``,
#: ``bad_mm + 10`` and ``bad_mm + 20``
OBJECTIVE_MM: list[float] = []


def thresholds(bad_mm: float) -> list[float]:
    """The frame-error thresholds (mm) the tune objective counts recall at."""
    return OBJECTIVE_MM or [bad_mm, bad_mm + 10.0, bad_mm + 20.0]


def tune_objective(
    tune: list[dict], weights: dict, bad_mm: float, smooth=(0, 0.0), radius: int = 0
) -> float:
    """Mean recall@10 % (relative to its :func:`ceiling`) over the tune sessions at each of
    :func:`thresholds`, counting only (session, threshold) pairs whose ceiling is
    at least 0.5: where more than a fifth of the frames are bad, every ranking's first 10 % is
    bad and says nothing about the ranking (on the suite most sessions saturate at 20 mm)."""
    out = []
    for d in tune:
        p = priority_of(d, weights, smooth)
        for thr in thresholds(bad_mm):
            bad = np.isfinite(d["err"]) & (d["err"] > thr)
            if ceiling(bad, d["refs"]) < 0.5:
                continue
            r = review.recall_at(
                p, bad, exclude=d["refs"], radius=radius, sequence_breaks=d["breaks"]
            )
            if np.isfinite(r):
                out.append(r / ceiling(bad, d["refs"]))
    return float(np.mean(out)) if out else 0.0


def coordinate_search(
    tune: list[dict], names: list[str], start: dict, bad_mm: float, quiet: bool = False
) -> dict:
    """Greedy coordinate ascent of :func:`tune_objective` over each weight in a small grid, from
    ``start`` (scale, weight) per term."""
    weights = dict(start)
    best = tune_objective(tune, weights, bad_mm)
    for _ in range(2):
        improved = False
        for k in names:
            scale, _ = weights[k]
            for w in (0.0, 0.5, 1.0, 2.0, 4.0):
                trial = dict(weights)
                trial[k] = (scale, round(float(w), 4))
                v = tune_objective(tune, trial, bad_mm)
                if v > best + 1e-9:
                    best, weights, improved = v, trial, True
        if not improved:
            break
    if not quiet:
        print(f"tune objective (weights) {best:.3f}")
    return weights


def spearman(priority: np.ndarray, err: np.ndarray, refs: np.ndarray) -> float:
    """Rank correlation of the priority with the frame's worst joint error over the non-reference
    frames with both (NaN with fewer than 3)."""
    from scipy.stats import spearmanr

    m = np.isfinite(priority) & np.isfinite(err)
    m[refs] = False
    if m.sum() < 3:
        return float("nan")
    return float(spearmanr(priority[m], err[m]).statistic)


def _sequence_name(folder: Path) -> str:
    """The name of the dataset folder a bench session ran on (``tune-fpha-1``). Not the session's
    work folder: one ``handanno bench`` run over several suite replicas names those
    ``tune-fpha-1``, ``tune-fpha-1-2``, ..., and holding out only one of them left the same
    sequence's other replicas in the fit (stop 59)."""
    try:
        return Path(json.loads((folder / "session.json").read_text())["dataset"]["path"]).name
    except (OSError, KeyError, ValueError, TypeError):
        return folder.parent.name


def family(d: dict) -> str:
    """The sequence a session runs on, whatever suite replica (seed) it comes from: the name of
    its dataset folder (``tune-fpha-1``)."""
    return d["sequence"]


def leave_one_out(tune: list[dict], choose, start: dict, bad_mm: float) -> list[dict]:
    """For each sequence of the tune part (all its replicas held out together): weights chosen
    by ``choose(sessions) -> weights`` on the other sequences; each held-out session's
    :func:`tune_objective` and rank correlation with ``start`` and with them."""
    out = []
    for held in tune:
        rest = [d for d in tune if family(d) != family(held)]
        w = choose(rest)
        p0 = review.evidence_priority(held["evidence"], start)
        p1 = review.evidence_priority(held["evidence"], w)
        out.append(
            {
                "session": held["name"],
                "start": round(tune_objective([held], start, bad_mm), 3),
                "chosen": round(tune_objective([held], w, bad_mm), 3),
                "spearman_start": round(spearman(p0, held["err"], held["refs"]), 3),
                "spearman_chosen": round(spearman(p1, held["err"], held["refs"]), 3),
                "informative": bool(_informative(held, bad_mm)),
            }
        )
        print("leave-one-out", out[-1], flush=True)
    return out


#: weights :func:`add_term` tries for the new term
ADD_TERM_GRID = (0.0, 0.5, 1.0, 2.0, 3.0, 4.0, 5.0, 8.0)


def add_term(sessions: list[dict], term: str, scale: float, bad_mm: float) -> dict:
    """:data:`BEFORE_WEIGHTS` with ``term`` at ``scale`` and the weight of
    :data:`ADD_TERM_GRID` with the best :func:`tune_objective` on ``sessions`` (the others
    unchanged: one number chosen, not a refit of every weight)."""

    def with_weight(w: float) -> dict:
        return {**BEFORE_WEIGHTS, term: (scale, w)}

    best = max(ADD_TERM_GRID, key=lambda w: tune_objective(sessions, with_weight(w), bad_mm))
    return with_weight(best)


def logistic_weights(sessions: list[dict], names: list[str], fit_mm: float) -> dict:
    """``{term: (scale, weight)}`` of a non-negative logistic regression (:func:`fit_logistic`)
    of "a joint more than ``fit_mm`` off" on ``log1p(x / scale)`` over the non-reference frames
    of ``sessions``, each term's scale its median there; terms of weight 0 left out."""

    def candidates(d):
        m = np.isfinite(d["err"])
        m[d["refs"]] = False
        return m

    ev_all = {k: np.concatenate([d["evidence"][k][candidates(d)] for d in sessions]) for k in names}
    scales = {}
    for k in names:
        v = ev_all[k][np.isfinite(ev_all[k]) & (ev_all[k] > 0)]
        scales[k] = max(float(np.median(v)), 1e-3) if v.size else 1.0
    x = features(ev_all, names, scales)
    y = np.concatenate([d["err"][candidates(d)] > fit_mm for d in sessions]).astype(np.float64)
    w = fit_logistic(x, y)
    out = {k: (round(scales[k], 4), round(float(w[i]), 4)) for i, k in enumerate(names)}
    return {k: v for k, v in out.items() if v[1] > 0}


def _informative(d: dict, bad_mm: float) -> bool:
    """Whether the session counts in :func:`tune_objective` at any threshold."""
    for thr in thresholds(bad_mm):
        bad = np.isfinite(d["err"]) & (d["err"] > thr)
        if bad.any() and ceiling(bad, d["refs"]) >= 0.5:
            return True
    return False


def search_smoothing(tune: list[dict], weights: dict, bad_mm: float) -> tuple[tuple, int]:
    """Grid over the temporal smoothing ``(radius, weight)`` and the pick's neighbour-suppression
    radius, by :func:`tune_objective`; the simplest setting wins ties."""
    best, arg = -1.0, ((0, 0.0), 0)
    for sr in (0, 1, 2, 4, 8):
        for sw in (0.0, 0.25, 0.5, 0.75) if sr else (0.0,):
            for r in (0, 1, 2, 4):
                v = tune_objective(tune, weights, bad_mm, (sr, sw), r)
                if v > best + 1e-9:
                    best, arg = v, ((sr, sw), r)
    print(f"tune objective (smoothing {arg[0]}, suppression radius {arg[1]}) {best:.3f}")
    return arg


def report_row(
    part: str, d: dict, weights: dict, smoothing: tuple, names: list[str], bad_mm: float
) -> dict:
    """One session's recalls at ``bad_mm`` and 40 mm, ceilings and rank correlations for the
    rankings compared (``smoothing`` = ``((radius, weight), suppression radius)``)."""
    smooth, radius = smoothing
    ex, br = d["refs"], d["breaks"]
    bad = np.isfinite(d["err"]) & (d["err"] > bad_mm)
    bad[ex] = False
    row = {
        "part": part,
        "session": d["name"],
        "frames": d["n"],
        "bad_frames": int(bad.sum()),
        "bad10_frames": int((np.isfinite(d["err"]) & (d["err"] > 10)).sum()),
        "ceiling": ceiling(bad, ex),
    }
    p_before = review.evidence_priority(d["evidence"], BEFORE_WEIGHTS)
    p_after = priority_of(d, weights, smooth)
    top = review.uniform_pick(d["n"], int(round(0.1 * d["n"])), exclude=ex)
    row["score"] = review.recall_at(d["score"], bad, exclude=ex)
    row["before"] = review.recall_at(p_before, bad, exclude=ex)
    row["weights_only"] = review.recall_at(
        review.evidence_priority(d["evidence"], weights), bad, exclude=ex
    )
    row["after"] = review.recall_at(p_after, bad, exclude=ex, radius=radius, sequence_breaks=br)
    row["uniform"] = float(bad[top].sum() / bad.sum()) if bad.any() else float("nan")
    bad40 = np.isfinite(d["err"]) & (d["err"] > 40.0)
    bad40[ex] = False
    row["bad40_frames"] = int(bad40.sum())
    row["ceiling40"] = ceiling(bad40, ex)
    row["before40"] = review.recall_at(p_before, bad40, exclude=ex)
    row["after40"] = review.recall_at(p_after, bad40, exclude=ex, radius=radius, sequence_breaks=br)
    row["uniform40"] = float(bad40[top].sum() / bad40.sum()) if bad40.any() else float("nan")
    for k, v in missed_counts(
        p_after, d["err"], d["shown_err"], ex, bad_mm, radius=radius, sequence_breaks=br
    ).items():
        row[f"{k}_frames"] = v
    row["spearman_before"] = spearman(p_before, d["err"], ex)
    row["spearman_after"] = spearman(p_after, d["err"], ex)
    for k in names:
        row[f"only_{k}"] = review.recall_at(
            np.nan_to_num(d["evidence"][k], nan=-1.0), bad, exclude=ex
        )
    print(
        part,
        d["name"],
        f"bad={row['bad_frames']} bad40={row['bad40_frames']}",
        f"missed={row['missed_frames']} (hidden only {row['missed_hidden_only_frames']})",
        " ".join(f"{k}={v:.2f}" for k, v in row.items() if isinstance(v, float)),
        flush=True,
    )
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tune", nargs="+", type=Path, required=True)
    ap.add_argument("--report", nargs="*", type=Path, default=[])
    ap.add_argument("--bad-mm", type=float, default=20.0)
    ap.add_argument("--fit-mm", type=float, default=10.0)
    ap.add_argument("--search", action="store_true", help="refine the weights on tune recall")
    ap.add_argument("--fixed", action="store_true", help="evaluate the committed constants")
    ap.add_argument("--cache", type=Path, help="folder to keep each session's evidence in")
    ap.add_argument("--loso", action="store_true", help="leave-one-sequence-out inside --tune")
    ap.add_argument(
        "--smoothing", action="store_true", help="search temporal smoothing and suppression too"
    )
    ap.add_argument(
        "--objective-mm",
        type=lambda t: [float(x) for x in t.split(",")],
        default=[],
        help="comma-separated thresholds of the tune objective (default: bad, +10, +20 mm)",
    )
    ap.add_argument(
        "--add-term",
        metavar="NAME:SCALE",
        help="keep BEFORE_WEIGHTS and choose only this term's weight (a grid) on the tune objective",
    )
    ap.add_argument("--json", type=Path, required=True)
    args = ap.parse_args()
    OBJECTIVE_MM[:] = args.objective_mm

    tune = [load(f, args.bad_mm, args.cache) for f in args.tune]
    report = [load(f, args.bad_mm, args.cache) for f in args.report]
    names = [k for k in tune[0]["evidence"] if all(k in d["evidence"] for d in tune + report)]

    weights = logistic_weights(tune, names, args.fit_mm)
    start = dict(BEFORE_WEIGHTS)
    choose = lambda sessions: logistic_weights(sessions, names, args.fit_mm)  # noqa: E731
    if args.search:  # from the weights before (new terms: weight 0), scales as fitted
        start = {k: (BEFORE_WEIGHTS.get(k, weights.get(k, (1.0, 0.0)))[0], 0.0) for k in names}
        start.update({k: v for k, v in BEFORE_WEIGHTS.items() if k in names})
        weights = coordinate_search(tune, names, start, args.bad_mm)
        choose = lambda sessions: coordinate_search(sessions, names, start, args.bad_mm, True)  # noqa: E731
    if args.add_term:
        term, scale = args.add_term.split(":")
        choose = lambda sessions: add_term(sessions, term, float(scale), args.bad_mm)  # noqa: E731
        weights = choose(tune)
    loso = leave_one_out(tune, choose, BEFORE_WEIGHTS, args.bad_mm) if args.loso else []
    weights = {k: v for k, v in weights.items() if v[1] > 0}
    smooth, radius = review.SMOOTH, review.SUPPRESS_RADIUS
    if args.smoothing:
        smooth, radius = search_smoothing(tune, weights, args.bad_mm)
    if args.fixed:  # report the committed constants (handanno_core.review)
        weights = dict(review.EVIDENCE_WEIGHTS)
    print("EVIDENCE_WEIGHTS =", json.dumps(weights))
    print("SMOOTH =", smooth, "SUPPRESS_RADIUS =", radius)

    rows = [
        report_row(part, d, weights, (smooth, radius), names, args.bad_mm)
        for part, data in (("tune", tune), ("report", report))
        for d in data
    ]
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(
        json.dumps(
            {
                "bad_mm": args.bad_mm,
                "fit_mm": args.fit_mm,
                "weights": weights,
                "smooth": list(smooth),
                "suppress_radius": radius,
                "objective_mm": thresholds(args.bad_mm),
                "before_weights": BEFORE_WEIGHTS,
                "leave_one_out": loso,
                "rows": rows,
            },
            indent=1,
        )
    )


#: the weights before this round: ``handanno_core.review.EVIDENCE_WEIGHTS`` before stop 48 added
#: the finger ambiguity (main 05a7d95), the others unchanged since
BEFORE_WEIGHTS = {k: v for k, v in review.EVIDENCE_WEIGHTS.items() if k != "ambiguity_mm"}

if __name__ == "__main__":
    main()
