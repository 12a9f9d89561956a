"""Freed solver arrays stay in the process while a solver runs and go back to the system after."""

from __future__ import annotations

import os

import numpy as np
import pytest

from handanno_core.memory import _LIBC, reuse_freed_memory

pytestmark = pytest.mark.skipif(
    _LIBC is None or not os.path.exists("/proc/self/statm"), reason="glibc on Linux only"
)


def _rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def _allocate_and_free(mb: int) -> None:
    a = np.ones(mb * 2**20 // 8)
    assert a[-1] == 1.0
    del a


def test_a_freed_large_array_is_kept_inside_and_returned_after():
    base = _rss_mb()
    _allocate_and_free(256)
    assert _rss_mb() < base + 64  # glibc's own way: unmapped when freed
    with reuse_freed_memory() as applied:
        assert applied
        _allocate_and_free(256)
        kept = _rss_mb()
        assert kept > base + 192  # still in the heap, for the next iteration
        _allocate_and_free(256)
        assert _rss_mb() < kept + 64  # reused, not allocated again
    assert _rss_mb() < base + 64  # trimmed on leaving


def test_nested_uses_keep_the_setting_until_the_outermost_ends():
    base = _rss_mb()
    with reuse_freed_memory():
        with reuse_freed_memory():
            pass
        _allocate_and_free(256)
        assert _rss_mb() > base + 192
    assert _rss_mb() < base + 64
