"""Learn the lift's pose prior (:mod:`handanno_core.pose_prior`) from real recorded hand motion.

Usage::

    .venv/bin/python benchmarks/learn_pose_prior.py [--data ../shared/data/real-motion]
        [--out handanno_core/data/pose_prior.json] [--shrink 0.01]

``msra21`` is learned from FPHA ``Subject_1`` **without** the sequences that drive the benchmark
suite's tune part (``tune-fpha-*``, :func:`handanno_core.suite.catalogue`), so a weight chosen on
the tune part is chosen on motion the prior has not seen; ``Subject_2`` drives the report part and
is never read. Only the mean and covariance of the bone directions are written (derived
statistics, about 40 kB), never the data. Also prints, per held-out FPHA sequence (the tune
part's), the share of its frames whose energy lies below the 99th percentile of the training
frames' energies.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from handanno_core import real_motion as rm
from handanno_core.pose_prior import (
    default_pose_prior_path,
    learn_pose_prior,
    prior_from_moments,
)
from handanno_core.skeleton import MSRA21
from handanno_core.suite import catalogue


def tune_fpha_motions(data: Path) -> set[str]:
    """``Subject_1/<action>/<n>`` of the suite's tune-part FPHA rows (seed 0)."""
    rows = catalogue(seed=0, real_motion=data)
    return {r.motion.split(":", 1)[1] for r in rows if r.motion.startswith("fpha:")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(rm.DEFAULT_REAL_MOTION))
    ap.add_argument("--out", default=str(default_pose_prior_path()))
    ap.add_argument("--shrink", type=float, default=0.01)
    ap.add_argument("--free", default="thumb_cmc", help="comma-separated joints left out")
    args = ap.parse_args()
    data = Path(args.data)
    held = tune_fpha_motions(data)
    train, held_files = [], []
    for f in rm.fpha_sequences(data, "Subject_1"):
        if f.stat().st_size == 0:
            continue
        rel = "/".join(f.parts[-4:-1])
        (held_files if rel in held else train).append(f)
    poses = np.concatenate([rm.load_fpha(f) for f in train])
    mean, cov = learn_pose_prior(MSRA21, poses, shrink=args.shrink)
    names = [MSRA21.joint_names[k] for k in MSRA21.angle_joints]
    free = [n for n in args.free.split(",") if n]
    keep = np.array([n not in free for n in names])
    prior = prior_from_moments("msra21", mean, cov, len(poses), keep)
    e_train = prior.energy(MSRA21, poses)
    p99 = float(np.percentile(e_train, 99))
    print(f"msra21: {len(poses)} frames of {len(train)} FPHA Subject_1 sequences; held out {held}")
    print(f"  energy median {np.median(e_train):.1f}, 99th percentile {p99:.1f}")
    for f in held_files:
        e = prior.energy(MSRA21, rm.load_fpha(f))
        print(
            f"  held out {'/'.join(f.parts[-4:-1])}: median {np.median(e):.1f}, "
            f"{100 * np.mean(e <= p99):.1f} % below the 99th percentile"
        )
    table = {
        "about": (
            "Gaussian over the bone directions at every angle joint (Skeleton.bone_directions, "
            "right hand): mean and covariance with shrink on the diagonal. Derived statistics "
            "only; written by benchmarks/learn_pose_prior.py."
        ),
        "layouts": {
            "msra21": {
                "source": "FPHA Subject_1 without the suite's tune-part sequences",
                "held_out": sorted(held),
                "frames": int(len(poses)),
                "shrink": args.shrink,
                "typical_energy": round(float(np.median(e_train)), 4),
                "joints": names,
                "free": free,
                "mean": [round(float(v), 6) for v in mean],
                "covariance": [[round(float(v), 7) for v in row] for row in cov],
            }
        },
    }
    Path(args.out).write_text(json.dumps(table, separators=(",", ":")) + "\n")
    print(f"wrote {args.out} ({Path(args.out).stat().st_size} bytes)")


if __name__ == "__main__":
    main()
