"""The crop cache built by several processes is the one a single process builds, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

from handanno_core.crops import locate_crops
from handanno_core.datasets import open_sequence
from handanno_core.datasets.base import BadFrameReport
from handanno_core.parallel import frame_ranges
from handanno_core.pipeline import ensure_crops, new_session
from handanno_core.session import CROPS_FILE, CROPS_META_FILE


@pytest.fixture(scope="module")
def three_sequences(tmp_path_factory):
    """Three different 16-frame recordings in one MSRA-layout dataset (breaks at 16 and 32), one
    frame of the second unreadable."""
    from handanno_core.synth import generate_sequence

    root = tmp_path_factory.mktemp("parallel-crops") / "data"
    for k in range(3):
        generate_sequence(root / f"g{k}", frames=16, seed=10 + k, progress=False, workers=1)
    (root / "g1" / "000005_depth.bin").write_bytes(b"\x00" * 10)  # frame 21: a bad file
    return root


def test_frame_ranges_cover_every_frame_and_start_at_breaks():
    assert frame_ranges(10, 2) == [(0, 2), (2, 4), (4, 6), (6, 8), (8, 10)]
    ranges = frame_ranges(100, 2, breaks=[5, 30, 31, 70])
    assert ranges[0][0] == 0 and ranges[-1][1] == 100
    assert all(b == c for (_, b), (c, _) in zip(ranges[:-1], ranges[1:], strict=True))
    assert {a for a, _ in ranges} <= {0, 5, 30, 31, 70}
    assert frame_ranges(100, 2, breaks=[]) == [(0, 100)]  # one sequence: one range
    assert frame_ranges(0, 2) == []


def test_parallel_location_equals_serial_with_the_same_bad_frames(three_sequences):
    seq = open_sequence(three_sequences)
    assert list(seq.sequence_breaks) == [16, 32]
    serial, parallel = BadFrameReport(), BadFrameReport()
    c1, spec1, box1 = locate_crops(seq, report=serial)
    c2, spec2, box2 = locate_crops(seq, report=parallel, workers=2)
    assert spec1 == spec2
    np.testing.assert_array_equal(c1, c2)
    np.testing.assert_array_equal(box1, box2)
    assert [str(e) for e in parallel.errors] == [str(e) for e in serial.errors]
    assert serial.frames == [21]


def test_parallel_crop_cache_equals_serial_bit_for_bit(three_sequences, tmp_path):
    one = new_session(tmp_path / "one", three_sequences, format="msra")
    two = new_session(tmp_path / "two", three_sequences, format="msra")
    crops1, centres1, boxes1 = ensure_crops(one, quiet=True)
    crops2, centres2, boxes2 = ensure_crops(two, quiet=True, workers=2)
    assert (tmp_path / "one" / CROPS_FILE).read_bytes() == (
        tmp_path / "two" / CROPS_FILE
    ).read_bytes()
    np.testing.assert_array_equal(centres1, centres2)
    np.testing.assert_array_equal(boxes1, boxes2)
    with (
        np.load(tmp_path / "one" / CROPS_META_FILE) as a,
        np.load(tmp_path / "two" / CROPS_META_FILE) as b,
    ):
        assert sorted(a.files) == sorted(b.files)
        for key in a.files:
            np.testing.assert_array_equal(a[key], b[key])
    assert np.all(np.asarray(crops2[21]) == 1.0)  # the bad frame is background
    assert np.asarray(crops2[22]).min() < 1.0  # its neighbour holds a hand
    one.close()
    two.close()


@pytest.fixture(scope="module")
def one_sequence(tmp_path_factory):
    """One 48-frame recording without breaks, frame 9 unreadable."""
    from handanno_core.synth import generate_sequence

    root = tmp_path_factory.mktemp("parallel-one") / "seq"
    generate_sequence(root, frames=48, seed=3, progress=False, workers=1)
    (root / "000009_depth.bin").write_bytes(b"\x00" * 10)
    return root


@pytest.mark.parametrize("overlap", [24, 0])
def test_one_sequence_located_in_pieces_equals_serial(one_sequence, monkeypatch, overlap):
    """Ranges cut inside the sequence meet where both locate alike (overlap 24), or the rest is
    located again from the previous range's hand (overlap 0: no frame to compare)."""
    from handanno_core import localize

    monkeypatch.setattr(localize, "LOCATE_PARALLEL_MIN_FRAMES", 0)
    monkeypatch.setattr(localize, "LOCATE_OVERLAP", overlap)
    seq = open_sequence(one_sequence)
    assert list(seq.sequence_breaks) == []
    serial, parallel = BadFrameReport(), BadFrameReport()
    one = localize.locate_hand_geometry(seq, report=serial)
    two = localize.locate_hand_geometry(seq, report=parallel, workers=2)
    np.testing.assert_array_equal(one, two)
    assert [str(e) for e in parallel.errors] == [str(e) for e in serial.errors]
    assert serial.frames == [9]
    assert np.isfinite(one[10:, 13]).any()


def _toy_chain(frames: range, bad: set[int], breaks: set[int], last_row=None):
    """A Markov hint chain like the hand locator's: a bump to 5 every 10th frame, else one less
    than the previous frame's row (0 without one: after a start, a break or a bad frame)."""
    rows, errs, prev = [], [], None if last_row is None else float(last_row[0])
    for f in frames:
        if f in breaks:
            prev = None
        if f in bad:
            rows.append([np.nan])
            errs.append(("seq", f, "bad"))
            prev = None
            continue
        v = 5.0 if f % 10 == 0 else (0.0 if prev is None else max(prev - 1.0, 0.0))
        rows.append([v])
        prev = v
    return np.asarray(rows, dtype=np.float64).reshape(-1, 1), errs


@pytest.mark.parametrize("overlap", [0, 1, 2, 6])
def test_pieces_of_a_markov_chain_merge_into_the_serial_chain(overlap):
    from handanno_core.localize import merge_located

    n, bad, breaks = 64, {17, 40}, {50}
    serial, serial_bad = _toy_chain(range(n), bad, breaks)
    cuts = [0, 13, 22, 31, 44, 50, 57, n]
    jobs = [
        (a, b if b == n or b in breaks else min(b + overlap, c))
        for a, b, c in zip(cuts[:-1], cuts[1:], [*cuts[2:], n], strict=True)
    ]
    done = [_toy_chain(range(a, stop), bad, breaks) for a, stop in jobs]
    calls = []

    def relocate(start, stop, last_row):
        calls.append(start)
        return _toy_chain(
            range(start, stop), bad, breaks, None if np.isnan(last_row[0]) else last_row
        )

    rows, errs = merge_located(jobs, done, n, breaks, relocate)
    np.testing.assert_array_equal(rows, serial)
    assert errs == serial_bad
    # frame 13 without a hint is 0, serially 2: the pieces meet at 15 when the overlap reaches
    # it, else the rest is located again from the end of the overlap
    assert (13 + overlap in calls) == (overlap < 3)
