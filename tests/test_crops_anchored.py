"""Crops placed again from annotated references (``localize.anchored_geometry``,
``pipeline.recrop_from_references``): where a lifted reference falls outside its crop, the
localization took the wrong end of an elongated arm region for the hand; the hint chain restarts
at the reference's joints and the annotated hand outvotes the shape cues.

The scene: an arm-like bar 420 mm long (MSRA camera, 600 mm away) whose one end is a solid disc,
nearest to the camera (a hand with its fingers closed), and whose other end is ragged (four
strips with gaps: what a sleeve's frayed end or a forearm's cut looks like to the shape cues).
Both shape cues and the rim call the disc the arm's stump, so the crop goes to the ragged end."""

from __future__ import annotations

import json

import numpy as np

from handanno_core import localize, pipeline
from handanno_core.crops import joints_inside_crops
from handanno_core.localize import (
    ANCHOR_VOTE,
    _geometry_middle,
    anchored_geometry,
    hand_geometry,
    locate_hand_geometry,
)
from handanno_core.session import CROPS_FILE, CROPS_META_FILE
from tests.test_crops_per_frame import CAM, FramesSequence, _scene

_BAR = (-150.0, 140.0, -30.0, 30.0, (590.0, 610.0))
_DISC = (-160.0, 0.0, 50.0, 588.0)  # the hand
_RAGGED = [(140.0, 215.0, y, y + 10.0, (610.0, 615.0)) for y in np.linspace(-32.0, 22.0, 4)]
DISC_X, RAGGED_X = -160.0, 180.0


def _frame() -> np.ndarray:
    return _scene(_BAR, _DISC, *_RAGGED)


def _disc_joints() -> np.ndarray:
    """21 points on the disc (mm): the hand's joints as a lift would give them."""
    a = np.linspace(0.0, 2.0 * np.pi, 21, endpoint=False)
    r = np.linspace(5.0, 40.0, 21)
    return np.stack([DISC_X + r * np.cos(a), r * np.sin(a), np.full(21, 595.0)], axis=1)


def test_an_annotated_hand_outvotes_the_shape_cues():
    depth = _frame()
    hint = _disc_joints().mean(axis=0)
    # no hint, and the previous frame's hand as a hint (TRACK_VOTE, less than the three cues
    # together): the ragged end
    assert _geometry_middle(hand_geometry(depth, CAM))[0] > 60.0
    assert _geometry_middle(hand_geometry(depth, CAM, prev_centre_mm=hint))[0] > 60.0
    # the annotated hand (ANCHOR_VOTE, more than the three cues together): the disc
    anchored = hand_geometry(depth, CAM, prev_centre_mm=hint, track_vote=ANCHOR_VOTE)
    assert _geometry_middle(anchored)[0] < -60.0


def test_anchored_geometry_relocates_the_frames_up_to_the_neighbouring_references():
    seq = FramesSequence([_frame() for _ in range(10)])
    geometry = locate_hand_geometry(seq)
    assert np.all(np.array([_geometry_middle(g)[0] for g in geometry]) > 60.0)
    # references at 0, 2, 5 and 9; the one at 5 was annotated on the disc
    out = anchored_geometry(seq, geometry, {5: _disc_joints()}, [0, 2, 5, 9])
    x = np.array([_geometry_middle(g)[0] for g in out])
    # backwards to the previous reference (2, whose crop held its joints), forwards to the next
    assert np.all(x[3:9] < -60.0)
    np.testing.assert_array_equal(out[[0, 1, 2, 9]], geometry[[0, 1, 2, 9]])
    # the anchor's row holds its joints' ray-angle box
    ang = _disc_joints()[:, :2] / _disc_joints()[:, 2:]
    assert np.all(out[5, 15:17] <= ang.min(axis=0)) and np.all(out[5, 17:19] >= ang.max(axis=0))
    # nothing to anchor: the geometry as it was
    np.testing.assert_array_equal(anchored_geometry(seq, geometry, {}, [0, 9]), geometry)
    assert out is not geometry and np.all(
        np.array([_geometry_middle(g)[0] for g in geometry]) > 60.0
    )


class _BrokenFrames(FramesSequence):
    """The same frames, two recordings: a break before frame 7."""

    @property
    def sequence_breaks(self):
        return [7]


def test_anchored_runs_stop_at_a_sequence_break():
    seq = _BrokenFrames([_frame() for _ in range(10)])
    geometry = locate_hand_geometry(seq)
    out = anchored_geometry(seq, geometry, {5: _disc_joints()}, [0, 5])
    x = np.array([_geometry_middle(g)[0] for g in out])
    assert np.all(x[1:7] < -60.0)  # back to reference 0, forwards to the break
    np.testing.assert_array_equal(out[[0, 7, 8, 9]], geometry[[0, 7, 8, 9]])


def _session(tmp_path, frames: int):
    """A session of ``frames`` copies of the scene (a folder of ``.npy`` depth maps)."""
    folder = tmp_path / "frames"
    folder.mkdir()
    for i in range(frames):
        np.save(folder / f"{i:03d}.npy", _frame())
    cam = {k: getattr(CAM, k) for k in ("fx", "fy", "cx", "cy", "width", "height")}
    (folder / "intrinsics.json").write_text(json.dumps(cam))
    return pipeline.new_session(tmp_path / "s", folder)


def test_propagate_places_the_crops_again_where_a_reference_falls_outside_its_own(tmp_path):
    session = _session(tmp_path, 10)
    crops0, centres0, _ = pipeline.ensure_crops(session, quiet=True)
    crops0 = np.array(crops0)
    joints = {f: np.tile(np.array([[RAGGED_X, 0.0, 612.0]]), (21, 1)) for f in (0, 2, 9)}
    joints[5] = _disc_joints()
    # references whose crops hold their joints: nothing changes
    held = {f: joints[f] for f in (0, 2, 9)}
    assert pipeline.recrop_from_references(session, held, quiet=True).size == 0
    changed = pipeline.recrop_from_references(session, joints, quiet=True)
    assert {3, 4, 5, 6, 7, 8} <= set(changed.tolist())
    # the cache is whole (its checksum matches: no rebuild) and holds the new crops
    cached = pipeline._cached_crops(
        session, session.folder / CROPS_FILE, session.folder / CROPS_META_FILE
    )
    assert isinstance(cached, tuple)
    crops1, centres1, _ = cached
    with np.load(session.folder / CROPS_META_FILE) as meta:
        box = np.asarray(meta["box_cubes_mm"])
    stack = np.stack([joints[f] for f in (0, 2, 5, 9)])
    assert joints_inside_crops(stack, centres1[[0, 2, 5, 9]], CAM, box[[0, 2, 5, 9]]).all()
    assert np.all(centres1[3:9, 0] < -40.0) and np.all(centres0[3:9, 0] > 40.0)
    # the frames up to the references that held theirs move only as far as smoothing takes them
    assert np.all(np.abs(centres1[[0, 1, 2, 9]] - centres0[[0, 1, 2, 9]]) < 5.0)
    crops1 = np.asarray(crops1)
    unchanged = np.setdiff1d(np.arange(10), changed)
    np.testing.assert_array_equal(crops1[unchanged], crops0[unchanged])
    assert all(not np.array_equal(crops1[f], crops0[f]) for f in range(3, 9))
    # a second call finds every reference held
    assert pipeline.recrop_from_references(session, joints, quiet=True).size == 0
    assert localize.ANCHOR_VOTE > 3.0  # two shape cues and the rim


def test_a_failed_rewrite_leaves_the_crop_cache_whole(tmp_path, monkeypatch):
    from handanno_core import crops as crops_module

    session = _session(tmp_path, 6)
    crops0 = np.array(pipeline.ensure_crops(session, quiet=True)[0])

    def full_disk(*args):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(crops_module, "_write_chunk", full_disk)
    joints = {0: np.tile(np.array([[RAGGED_X, 0.0, 612.0]]), (21, 1)), 3: _disc_joints()}
    try:
        pipeline.recrop_from_references(session, joints, quiet=True)
    except OSError as exc:
        assert "No space left" in str(exc)
    else:
        raise AssertionError("the write error must reach the caller")
    assert not list(session.folder.glob("*.tmp.npy"))
    cached = pipeline._cached_crops(
        session, session.folder / CROPS_FILE, session.folder / CROPS_META_FILE
    )
    assert isinstance(cached, tuple)  # the old cache, whole and consistent
    np.testing.assert_array_equal(np.asarray(cached[0]), crops0)
