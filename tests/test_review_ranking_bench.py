"""The review-ranking bench's count of the bad frames its ranking finds and misses."""

import numpy as np

from tests.benchmark_scripts import load_benchmark

bench = load_benchmark("bench_review_ranking")


def test_missed_counts_split_found_and_missed_bad_frames_by_what_the_depth_shows():
    n = 20
    err = np.full(n, 5.0)
    err[[3, 4, 10, 15]] = 30.0  # bad frames
    err[0] = 50.0  # bad, but a reference: never counted
    shown_err = np.full(n, 5.0)
    shown_err[[4, 15]] = 25.0  # bad in a joint the depth shows
    priority = np.zeros(n)
    priority[[3, 4, 0]] = [3.0, 2.0, 9.0]  # the first 10 % (2 frames, the reference skipped)
    out = bench.missed_counts(priority, err, shown_err, np.array([0]), 20.0)
    assert out == {"found": 2, "found_hidden_only": 1, "missed": 2, "missed_hidden_only": 1}


def test_missed_counts_treat_an_unknown_shown_error_as_not_shown():
    err = np.array([30.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0])
    shown_err = np.array([np.nan] + [0.0] * 9)
    out = bench.missed_counts(np.arange(10.0), err, shown_err, np.array([], dtype=int), 20.0)
    assert out == {"found": 0, "found_hidden_only": 0, "missed": 1, "missed_hidden_only": 1}
