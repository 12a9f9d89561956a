"""The benchmark suite: sequences to tune on and disjoint sequences to report on.

``handanno suite OUT_DIR`` renders every sequence of :func:`catalogue` into ``OUT_DIR/<name>/``
(MSRA layout + ``camera.json`` + ``synth.json``, as ``handanno synth``) and writes
``OUT_DIR/suite.json``: for each sequence its name, part, folder, frame count, generator settings and
measured statistics (mean joint step, hand size; for fitted recorded motion the inverse-kinematics
residual). Deterministic by seed.

What varies (each row of :func:`catalogue`):

* today's smooth generator motion (:func:`handanno_core.synth.synthesize_motion`), today's hand;
* hand shape: overall size 0.8-1.2x, per-finger proportions, finger radii and palm breadth drawn
  from adult hand measurements (:func:`handanno_core.synth.make_varied_hand_model`);
* fast motion: the generator timed for a mean joint step of >= 10 mm per frame (30 fps);
* real recorded motion (:mod:`handanno_core.real_motion`): FPHA 21-joint sequences rendered as
  recorded (bones from the sequence), NYU (14 joints) and ICVL (16 joints) trajectories after the
  inverse-kinematics fit of the 21-joint hand;
* sensors: Kinect-like (disparity quantization, flying pixels) and SR300-like (holes, ragged edges),
  640x480 as well as 320x240 intrinsics;
* the arm: straight, over the wrist's range of motion, top-down (every in-plane direction) and
  egocentric (the elbow nearer to the camera than the hand), with and without a sleeve.

The split (see :data:`SPLIT_NOTE`): constants are chosen on the ``tune`` part only; figures are
reported on the ``report`` part only. The parts share no motion source (FPHA subject 1 and NYU
motion and ICVL test sequence 2 are tune-only; FPHA subject 2 and ICVL test sequence 1 are
report-only; generator seeds differ) and no hand (every synthetic hand is drawn from its own seed).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from . import real_motion as rm
from .camera import MSRA_CAMERA, NYU_CAMERA, CameraIntrinsics
from .skeleton import MSRA21
from .synth import (
    SENSORS,
    make_hand_model,
    make_varied_hand_model,
    pose_arm,
    synthesize_motion,
    write_sequence,
)

PARTS = ("tune", "report")
SPLIT_NOTE = (
    "Constants (weights, offsets, limits, thresholds, default strategy and aligner) are chosen on "
    "the tune part only; figures are reported on the report part only. The parts share no motion "
    "source (tune: generator seeds 1xx, FPHA Subject_1, NYU test frames of the first person, ICVL "
    "test sequence 2; report: generator seeds 2xx, FPHA Subject_2, ICVL test sequence 1) and no "
    "hand shape."
)
#: cameras by name: 320x240 (MSRA / ICVL-like and a Kinect's 320x240 mode) and 640x480
CAMERAS: dict[str, CameraIntrinsics] = {
    "msra": MSRA_CAMERA,
    "icvl": rm.ICVL_LABEL_CAMERA,
    "kinect640": NYU_CAMERA,
    "kinect320": CameraIntrinsics(fx=294.0, fy=293.5, cx=160.0, cy=120.0, width=320, height=240),
    "sr300": rm.FPHA_CAMERA,
}
#: fast generator motion: peak joint speed per transition (mm/frame) and holds (frames), chosen so
#: that the mean joint step is >= 10 mm/frame (real fast hand motion, ~13 mm/frame at 30 fps)
FAST_SPEED_MM = (42.0, 58.0)
FAST_HOLD_FRAMES = (0, 1)
#: FPHA sequences eligible for the suite (frames), to keep the suite's size modest
FPHA_FRAMES = (200, 500)


@dataclass(frozen=True)
class SuiteSequence:
    """One sequence of the suite and how it is generated (its row of ``suite.json``)."""

    name: str
    part: str  # "tune" | "report"
    motion: (
        str  # "smooth" | "fast" | "fpha:<Subject>/<action>/<n>" | "nyu:<first frame>" | "icvl:<n>"
    )
    frames: int  # before --frames-scale (recorded motion: at most the recording's length)
    seed: int
    hand: str = "default"  # "default" (today's generator hand) | "varied" | "recorded"
    sensor: str = "msra"
    camera: str = "msra"
    depth_mm: float | None = None  # move the hand to this median distance
    arm: str = "hand"
    sleeve: bool = False


def _fpha_pick(root: Path, subject: str, count: int, seed: int) -> list[str]:
    """``count`` FPHA sequences of ``subject`` with :data:`FPHA_FRAMES` frames, distinct actions."""
    eligible = []
    for path in rm.fpha_sequences(root, subject):
        with open(path) as fh:
            n = sum(1 for line in fh if line.strip())
        if FPHA_FRAMES[0] <= n <= FPHA_FRAMES[1]:
            eligible.append(path)
    rng = np.random.default_rng([seed, 606])
    picked: list[str] = []
    for i in rng.permutation(len(eligible)):
        rel = eligible[i].parent.relative_to(root / "fpha")
        if all(Path(p).parts[1] != rel.parts[1] for p in picked):
            picked.append(str(rel))
        if len(picked) == count:
            break
    return picked


def catalogue(seed: int = 0, real_motion: Path | None = None) -> list[SuiteSequence]:
    """Every sequence of the suite for ``seed`` (tune part first). Recorded motion is listed only
    when ``real_motion`` (default :data:`handanno_core.real_motion.DEFAULT_REAL_MOTION`) exists."""
    root = Path(real_motion) if real_motion is not None else rm.DEFAULT_REAL_MOTION
    s = 1000 * seed
    v, kin, sr = "varied", "kinect", "sr300"
    # fmt: off
    rows = [  # name, part, motion, frames, seed, then how the frames are rendered
        SuiteSequence("tune-smooth", "tune", "smooth", 600, s + 101),
        SuiteSequence("tune-shape-fast", "tune", "fast", 400, s + 102, hand=v),
        SuiteSequence("tune-kinect640-wrist", "tune", "smooth", 500, s + 103, hand=v, sensor=kin,
                      camera="kinect640", depth_mm=650.0, arm="wrist", sleeve=True),
        SuiteSequence("tune-sr300-egocentric", "tune", "smooth", 500, s + 104, hand=v, sensor=sr,
                      camera="msra", arm="egocentric"),
        SuiteSequence("report-smooth", "report", "smooth", 600, s + 201),
        SuiteSequence("report-shape", "report", "smooth", 600, s + 202, hand=v),
        SuiteSequence("report-shape-fast", "report", "fast", 400, s + 203, hand=v),
        SuiteSequence("report-sr300-topdown", "report", "smooth", 500, s + 204, hand=v, sensor=sr,
                      camera="sr300", arm="top-down", sleeve=True),
        SuiteSequence("report-kinect320-egocentric", "report", "smooth", 500, s + 205, hand=v,
                      sensor=kin, camera="kinect320", depth_mm=650.0, arm="egocentric",
                      sleeve=True),
    ]
    # fmt: on
    if root.is_dir():
        for part, subject in (("tune", "Subject_1"), ("report", "Subject_2")):
            for i, rel in enumerate(_fpha_pick(root, subject, 2, seed)):
                rows.append(
                    SuiteSequence(
                        f"{part}-fpha-{i + 1}",
                        part,
                        f"fpha:{rel}",
                        FPHA_FRAMES[1],
                        s + (110 if part == "tune" else 210) + i,
                        hand="recorded",
                        sensor="sr300",
                        camera="sr300",
                        arm="egocentric",
                    )
                )
        rows.append(
            SuiteSequence(
                "tune-nyu",
                "tune",
                "nyu:0",
                600,
                s + 120,
                hand="recorded",
                sensor="kinect",
                camera="kinect640",
                arm="wrist",
            )
        )
        # ICVL's labels jump (a mean joint step of 8-9 mm, 7 % of steps > 20 mm, repeated frames):
        # the tune part has its second test sequence, the report part its first
        rows.append(
            SuiteSequence(
                "tune-icvl",
                "tune",
                "icvl:2",
                894,
                s + 130,
                hand="recorded",
                camera="icvl",
                arm="wrist",
            )
        )
        rows.append(
            SuiteSequence(
                "report-icvl",
                "report",
                "icvl:1",
                702,
                s + 220,
                hand="recorded",
                camera="icvl",
                arm="wrist",
                sleeve=True,
            )
        )
    return sorted(rows, key=lambda r: (PARTS.index(r.part), r.name))


def _move_to_depth(joints: np.ndarray, depth_mm: float) -> np.ndarray:
    """Joints ``(N, J, 3)`` moved along each frame's ray through the hand centre so that the median
    hand centre is ``depth_mm`` away; the hand's image position stays (its image size shrinks)."""
    centre = joints.mean(axis=1)
    dz = depth_mm - float(np.median(centre[:, 2]))
    shift = centre * (dz / centre[:, 2])[:, None]
    return joints + shift[:, None, :]


def mean_joint_step_mm(joints: np.ndarray) -> float:
    """Mean over frames and joints of the distance a joint moves between frames (mm/frame)."""
    return float(np.linalg.norm(np.diff(joints, axis=0), axis=-1).mean())


def render_suite_sequence(
    row: SuiteSequence,
    out_dir: Path,
    *,
    frames_scale: float = 1.0,
    real_motion: Path | None = None,
    workers: int = 2,
    progress: bool = False,
) -> dict:
    """Render one row into ``out_dir``; returns its ``suite.json`` entry (settings + statistics)."""
    root = Path(real_motion) if real_motion is not None else rm.DEFAULT_REAL_MOTION
    frames = max(30, int(round(row.frames * frames_scale)))
    stats: dict = {}
    source, _, arg = row.motion.partition(":")
    if source in ("smooth", "fast"):
        model = (
            make_hand_model(row.seed) if row.hand == "default" else make_varied_hand_model(row.seed)
        )
        fast = (
            {"speed_mm": FAST_SPEED_MM, "hold_frames": FAST_HOLD_FRAMES} if source == "fast" else {}
        )
        motion = synthesize_motion(frames, row.seed, model=model, **fast)
        joints, rotation = motion.joints_mm, motion.rotation
    elif source == "fpha":
        joints = rm.load_fpha(root / "fpha" / arg / "skeleton.txt")[:frames]
        model = rm.model_of_joints(joints)
        rotation = rm.rotation_of_joints(joints)
    elif source in ("nyu", "icvl"):
        if source == "nyu":
            start = int(arg)
            targets, markers = rm.load_nyu(root)[start : start + frames], rm.NYU14_MARKERS
        else:
            # the ICVL labels measure as a left hand: mirrored (x -> -x) for the right-hand model
            targets, markers = rm.load_icvl(root, int(arg))[:frames], rm.ICVL16_MARKERS
            targets = targets * np.array([-1.0, 1.0, 1.0])
        fit = rm.fit_skeleton(targets, markers)
        model, joints, rotation = fit.model, fit.joints_mm, fit.rotation
        stats["ik_residual_mm"] = fit.summary()
        stats["recorded_mean_joint_step_mm"] = round(mean_joint_step_mm(targets), 3)
    else:
        raise ValueError(f"{row.name}: unknown motion {row.motion!r}")
    if row.depth_mm is not None:
        joints = _move_to_depth(joints, row.depth_mm)
    joints, rotation, forearm = pose_arm(joints, rotation, row.arm, row.seed)
    camera = CAMERAS[row.camera]
    entry = {**asdict(row), "frames": len(joints), "path": row.name}
    stats.update(
        {
            "mean_joint_step_mm": round(mean_joint_step_mm(joints), 3),
            "bone_lengths_mm": [round(float(x), 2) for x in model.bone_lengths_mm],
            "hand_length_mm": round(float(model.bone_lengths_mm[4:8].sum()), 1),
            "median_depth_mm": round(float(np.median(joints[..., 2])), 1),
        }
    )
    entry["stats"] = stats
    write_sequence(
        out_dir / row.name,
        model,
        joints,
        rotation,
        seed=row.seed,
        camera=camera,
        sensor=SENSORS[row.sensor],
        forearm=forearm,
        sleeve=row.sleeve,
        info={"suite": entry},
        workers=workers,
        progress=progress,
    )
    return entry


def generate_suite(
    out_dir: str | Path,
    *,
    seed: int = 0,
    part: str = "all",
    frames_scale: float = 1.0,
    real_motion: Path | None = None,
    workers: int = 2,
    progress: bool = True,
) -> dict:
    """Render the suite (``part``: tune, report or all) into ``out_dir`` and write ``suite.json``.

    Returns the manifest: ``seed``, ``frames_scale``, ``split`` (:data:`SPLIT_NOTE`) and
    ``sequences`` (one entry per sequence: name, part, path relative to ``out_dir``, frames,
    settings, stats). A manifest already in ``out_dir`` keeps its other part's entries, so the two
    parts can be generated by separate calls.
    """
    if part not in (*PARTS, "all"):
        raise ValueError(f"part must be tune, report or all, got {part!r}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    manifest_path = out / "suite.json"
    old = json.loads(manifest_path.read_text()) if manifest_path.exists() else None
    keep = []
    if old and old.get("seed") == seed and old.get("frames_scale") == frames_scale:
        keep = [e for e in old.get("sequences", []) if part != "all" and e["part"] != part]
    entries = []
    for row in catalogue(seed, real_motion):
        if part != "all" and row.part != part:
            continue
        if progress:
            print(f"suite: {row.name} ({row.motion})", flush=True)
        entries.append(
            render_suite_sequence(
                row,
                out,
                frames_scale=frames_scale,
                real_motion=real_motion,
                workers=workers,
                progress=progress,
            )
        )
    manifest = {
        "seed": seed,
        "frames_scale": frames_scale,
        "split": SPLIT_NOTE,
        "skeleton": MSRA21.name,
        "sequences": sorted(keep + entries, key=lambda e: (PARTS.index(e["part"]), e["name"])),
    }
    manifest_path.write_text(json.dumps(manifest, indent=1))
    return manifest


def read_suite(folder: str | Path, part: str = "all") -> list[tuple[str, str, Path]]:
    """``(name, part, path)`` of the sequences of a suite folder (``part``: tune, report or all)."""
    folder = Path(folder)
    path = folder / "suite.json"
    try:
        manifest = json.loads(path.read_text())
        rows = [(e["name"], e["part"], folder / e["path"]) for e in manifest["sequences"]]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"{path}: not a readable suite manifest ({exc})") from exc
    if part not in (*PARTS, "all"):
        raise ValueError(f"part must be tune, report or all, got {part!r}")
    chosen = [r for r in rows if part == "all" or r[1] == part]
    if not chosen:
        raise ValueError(f"{path}: no {part} sequences")
    return chosen


def is_suite(folder: str | Path) -> bool:
    """True when ``folder`` holds a ``suite.json``."""
    return (Path(folder) / "suite.json").is_file()
