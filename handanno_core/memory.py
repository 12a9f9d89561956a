"""glibc's malloc kept from handing large freed arrays back to the system inside a solver loop.

A solver iteration allocates and frees arrays of tens to hundreds of MB (normal equations, the
band, Jacobians). glibc serves blocks that large by ``mmap`` and returns them with ``munmap``
when freed, so every iteration pays the page faults of fresh memory again; on some machines (a
sandboxed kernel) that costs more than the arithmetic. :func:`reuse_freed_memory` raises the
mmap and trim thresholds while a solver runs, so freed blocks stay in the heap and are reused,
then restores glibc's adapted defaults and trims the heap. Elsewhere than on glibc it does
nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import threading
from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ["reuse_freed_memory"]

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
#: mallopt's ceiling for both thresholds (a C int)
_KEEP = 2**31 - 1
#: what glibc's dynamic thresholds settle at after large frees on 64-bit systems
#: (DEFAULT_MMAP_THRESHOLD_MAX, and twice it for trimming)
_MMAP_DEFAULT = 32 * 2**20
_TRIM_DEFAULT = 2 * _MMAP_DEFAULT

_lock = threading.Lock()
_depth = 0


def _libc():
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        return libc if hasattr(libc, "mallopt") and hasattr(libc, "malloc_trim") else None
    except OSError:
        return None


_LIBC = _libc()


@contextmanager
def reuse_freed_memory() -> Iterator[bool]:
    """Inside: freed blocks of any size up to 2 GB stay in the process for reuse (yields whether
    glibc took the setting). On leaving the outermost one: the thresholds back at glibc's adapted
    defaults and free heap memory returned to the system (``malloc_trim``). Peak memory is the
    same; memory between the peaks is not returned until the end."""
    global _depth
    libc = _LIBC
    with _lock:
        _depth += 1
        applied = bool(
            libc is not None
            and libc.mallopt(_M_MMAP_THRESHOLD, ctypes.c_int(_KEEP))
            and libc.mallopt(_M_TRIM_THRESHOLD, ctypes.c_int(_KEEP))
        )
    try:
        yield applied
    finally:
        with _lock:
            _depth -= 1
            if libc is not None and _depth == 0:
                libc.mallopt(_M_MMAP_THRESHOLD, ctypes.c_int(_MMAP_DEFAULT))
                libc.mallopt(_M_TRIM_THRESHOLD, ctypes.c_int(_TRIM_DEFAULT))
                libc.malloc_trim(ctypes.c_size_t(0))
