"""One shared switch for BLAS threading.

SLSQP (lift) and the banded solves (refine) make many tiny LAPACK calls; a multithreaded OpenBLAS
spends more time waking its threads than computing (figures:
``benchmarks/results/design_measurements.md``). Wrap those solver calls in :func:`single_blas_thread`.
"""

from __future__ import annotations

from threadpoolctl import threadpool_limits


def single_blas_thread() -> threadpool_limits:
    """Context manager limiting BLAS/LAPACK to one thread in this process."""
    return threadpool_limits(limits=1, user_api="blas")
