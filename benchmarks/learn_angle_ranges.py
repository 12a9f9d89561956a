"""Learn joint-angle ranges (and template bone lengths) from real recorded hand motion.

Usage::

    .venv/bin/python benchmarks/learn_angle_ranges.py [--data ../shared/data/real-motion]
        [--out handanno_core/data/angle_ranges.json] [--low 0.25] [--high 99.75]

Reads the joint trajectories in ``real-motion/`` (README there; never copied into the repository):

* ``msra21`` from FPHA ``Subject_1`` (21 joints, ~20k frames; ``Subject_2`` is held out for
  benchmarks/bench_lift.py): FPHA's joint order is mapped onto
  MSRA-21 (:data:`handanno_core.skeleton.FPHA_TO_MSRA21`, read by :mod:`handanno_core.real_motion`; FPHA's thumb "MCP" is the CMC-side joint, as MSRA's first thumb
  joint);
* ``nyu14`` from the NYU test labels (u, v, d back-projected with the NYU Kinect intrinsics);
* ``icvl16`` from the two ICVL test sequences (u, v, d back-projected with f = 241).

For every joint with a parent and a single child (the joints ``Skeleton.joint_angles`` measures)
the flexion and abduction are computed exactly as the lift measures them, and the ``low``/``high``
percentiles are stored, for a right hand: labels that measure as a mirrored hand (median finger
flexion < 0: the ICVL labels) are measured with the left-hand palm normal (``mirrored`` in the
table). Per layout the median bone lengths (mm) are stored as well (the template of
layouts that have none). Only these derived statistics are written (a few kB), never the data.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np

from handanno_core import real_motion as rm
from handanno_core.skeleton import (
    ICVL16,
    MSRA21,
    NYU14,
    Skeleton,
    default_angle_ranges_path,
)


def load_fpha(data: Path, subjects: tuple[str, ...] = ("Subject_1",)) -> np.ndarray:
    """FPHA frames ``(N, 21, 3)`` mm of ``subjects`` in MSRA-21 order (empty files skipped)."""
    files = [f for s in subjects for f in rm.fpha_sequences(data, s) if f.stat().st_size > 0]
    if not files:
        raise FileNotFoundError(f"{data / 'fpha'}: no */*/*/skeleton.txt")
    return np.concatenate([rm.load_fpha(f) for f in files])


def load_layout(layout: str, data: Path) -> np.ndarray:
    """The recorded frames ``(N, J, 3)`` mm the table of ``layout`` is learned from."""
    if layout == "msra21":
        return load_fpha(data)
    if layout == "nyu14":
        return rm.load_nyu(data)
    if layout == "icvl16":
        return np.concatenate([rm.load_icvl(data, 1), rm.load_icvl(data, 2)])
    raise ValueError(f"no recorded motion for layout {layout!r}")


def measurable(skeleton: Skeleton) -> Skeleton:
    """The layout with every joint that has a parent and one child marked as an angle joint."""
    par = skeleton.parent_array
    nchild = np.bincount(par[par >= 0], minlength=skeleton.num_joints)
    nan = (float("nan"), float("nan"))
    lim = tuple(
        (0.0, 0.0) if par[k] >= 0 and nchild[k] == 1 else nan for k in range(skeleton.num_joints)
    )
    return dataclasses.replace(skeleton, flexion_limits_deg=lim, abduction_limits_deg=lim)


def _outward(lo_hi: np.ndarray) -> list[float]:
    """Round a range to 0.01 degrees outwards (never excluding a value it contained)."""
    return [float(np.floor(lo_hi[0] * 100) / 100), float(np.ceil(lo_hi[1] * 100) / 100)]


def learn(skeleton: Skeleton, poses: np.ndarray, low: float, high: float, source: str) -> dict:
    sk = measurable(skeleton)
    flex, abd = sk.joint_angles(poses)
    # ranges are stored for a right hand (the lift's default); a dataset whose labels measure as
    # a mirrored hand (fingers flexing away from the palm normal) is measured as a left hand
    fingers = [i for i, k in enumerate(sk.angle_joints) if "thumb" not in sk.joint_names[k]]
    mirrored = bool(np.median(flex[:, fingers]) < 0)
    if mirrored:
        # a mirror keeps flexion measured with the mirrored palm normal, and negates abduction
        flex, abd = sk.joint_angles(poses, right_hand=False)
        abd = -abd
    joints = {}
    for i, k in enumerate(sk.angle_joints):
        joints[sk.joint_names[k]] = {
            "flexion": _outward(np.percentile(flex[:, i], [low, high])),
            "abduction": _outward(np.percentile(abd[:, i], [low, high])),
        }
    bones = np.median(sk.bone_lengths(poses), axis=0)
    return {
        "source": source,
        "frames": int(len(poses)),
        "mirrored": mirrored,
        "joints": joints,
        "bone_lengths_mm": [round(float(b), 1) for b in bones],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(rm.DEFAULT_REAL_MOTION))
    ap.add_argument("--out", default=str(default_angle_ranges_path()))
    ap.add_argument("--low", type=float, default=0.25)
    ap.add_argument("--high", type=float, default=99.75)
    args = ap.parse_args()
    data = Path(args.data)
    table = {
        "about": (
            "Joint-angle ranges (degrees, Skeleton.joint_angles definition, right-hand palm normal) "
            f"= the {args.low} and {args.high} percentiles over real recorded motion, and median "
            "bone lengths (mm). Derived statistics only; written by benchmarks/learn_angle_ranges.py."
        ),
        "percentiles": [args.low, args.high],
        "layouts": {
            "msra21": learn(
                MSRA21, load_layout("msra21", data), args.low, args.high, "FPHA Subject_1"
            ),
            "nyu14": learn(
                NYU14, load_layout("nyu14", data), args.low, args.high, "NYU test labels"
            ),
            "icvl16": learn(
                ICVL16, load_layout("icvl16", data), args.low, args.high, "ICVL test_seq_1+2"
            ),
        },
    }
    Path(args.out).write_text(json.dumps(table, indent=1) + "\n")
    for name, lay in table["layouts"].items():
        print(f"{name}: {lay['frames']} frames from {lay['source']}, mirrored {lay['mirrored']}")
        for joint, r in lay["joints"].items():
            print(f"  {joint:12s} flexion {r['flexion']} abduction {r['abduction']}")
        print(f"  bones {lay['bone_lengths_mm']}")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
