"""The review ranking's chain terms along the selection's forest (committed) vs along the candidate
chain each frame kept (``results.npz`` ``source``), with the committed ``EVIDENCE_WEIGHTS``.

Input: finished bench sessions (``handanno bench --work-dir``), e.g. the tune part at 5 % forest.
For each session ``hops``, ``gap`` and ``drift_mm`` of :func:`handanno_core.review.review_evidence`
are recomputed along the forest of :func:`handanno_core.pipeline.propagation_forests` whose parent
is the frame's stored source (the kept candidate; depth and root in that forest), the other terms
kept. Printed: frames that kept another chain than the selection's parent, frames in source
2-cycles (5 from 6 and 6 from 5), and for both variants the tune objective of
``bench_review_ranking`` (recall@10 % over its ceiling at 10-40 mm) and the mean rank correlation
with the frame error.

    python benchmarks/bench_review_source.py /tmp/work/tune  # folders holding */forest-0.05/
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_review_ranking as brr  # noqa: E402

from handanno_core import review  # noqa: E402
from handanno_core.export import best_joints  # noqa: E402
from handanno_core.forest import depths, roots  # noqa: E402
from handanno_core.pipeline import propagation_forests  # noqa: E402
from handanno_core.prefill import cached_crops  # noqa: E402
from handanno_core.session import Session  # noqa: E402


def kept_chain_evidence(folder: Path, d: dict) -> tuple[dict, int, int]:
    """``d``'s evidence with hops/gap/drift along the kept candidate forests; the number of
    frames that kept another chain than the selection's parent and of frames in 2-cycles."""
    with Session.open(folder) as s:
        res = s.load_results()
        src, par = res["source"], s.parent
        forests = propagation_forests(s)
        n = len(par)
        rows = np.arange(n)
        match = forests == src[None]
        k = np.where(match.any(axis=0), np.argmax(match, axis=0), 0)
        root = np.stack([roots(f) for f in forests])[k, rows]
        ev = dict(d["evidence"])
        ev["hops"] = np.stack([depths(f) for f in forests])[k, rows].astype(np.float64)
        ev["gap"] = np.abs(rows - root).astype(np.float64)
        ev["drift_mm"] = review.centre_drift(best_joints(res)[0], cached_crops(s)[1], root)
    ok = src >= 0
    other = int(np.sum(ok & (par >= 0) & (src != par)))
    cycles = int(np.sum(ok & (src[np.where(ok, src, 0)] == rows)))
    return ev, other, cycles


def main() -> None:
    brr.OBJECTIVE_MM[:] = [10.0, 15.0, 20.0, 30.0, 40.0]
    folders = sorted(p.parent for p in Path(sys.argv[1]).rglob("forest-0.05/session.json"))
    old, new = [], []
    for folder in folders:
        d = brr.load(folder, 20.0)
        ev, other, cycles = kept_chain_evidence(folder, d)
        nonref = int(np.sum(np.isfinite(d["evidence"]["hops"]) & (d["evidence"]["hops"] > 0)))
        print(f"{d['name']}: {other}/{nonref} frames kept another chain, {cycles} in 2-cycles")
        old.append(d)
        new.append(dict(d, evidence=ev))
    w = review.EVIDENCE_WEIGHTS
    for name, sessions in (("selection forest", old), ("kept chain", new)):
        obj = brr.tune_objective(sessions, w, 20.0)
        rho = [brr.spearman(brr.priority_of(d, w, (0, 0.0)), d["err"], d["refs"]) for d in sessions]
        print(f"{name}: objective {obj:.3f}, mean rank correlation {np.nanmean(rho):.3f}")


if __name__ == "__main__":
    main()
