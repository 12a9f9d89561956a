"""Tests of handanno_core.aggregate: timeline bins over a long session."""

from __future__ import annotations

import numpy as np
import pytest

from handanno_core.aggregate import bin_edges, summarize_bins


def test_edges_cover_all_frames_and_never_straddle_a_break():
    e = bin_edges(76_000, 500, breaks=[500, 1000, 75_999])
    assert e[0] == 0 and e[-1] == 76_000 and np.all(np.diff(e) > 0)
    assert {500, 1000, 75_999} <= set(e.tolist())
    assert len(e) - 1 <= 503
    assert bin_edges(3, 10).tolist() == [0, 1, 2, 3]
    assert bin_edges(0, 10).tolist() == [0]


def test_summaries_match_a_per_bin_loop_with_nan_and_flags():
    rng = np.random.default_rng(0)
    v = rng.normal(size=1000)
    v[rng.random(1000) < 0.2] = np.nan
    v[300:340] = np.nan  # a bin without any value
    v[700] = v[701] = 9.0  # tie: the first frame is the one to jump to
    flags = rng.random(1000) < 0.05
    e = bin_edges(1000, 25)
    s = summarize_bins(v, e, flags)
    for k, (a, b) in enumerate(zip(e[:-1], e[1:], strict=True)):
        part = v[a:b]
        fin = np.isfinite(part)
        assert s.count[k] == b - a and s.finite[k] == fin.sum() and s.flagged[k] == flags[a:b].sum()
        if fin.any():
            assert s.mean[k] == pytest.approx(part[fin].mean())
            assert s.max[k] == part[fin].max() and s.min[k] == part[fin].min()
            assert s.argmax[k] == a + int(np.nanargmax(part))
        else:
            assert np.isnan(s.mean[k]) and np.isnan(s.max[k]) and s.argmax[k] == -1
    assert s.argmax[np.searchsorted(e, 700, side="right") - 1] == 700
    with pytest.raises(ValueError, match="edges"):
        summarize_bins(v, np.array([0, 10]))
