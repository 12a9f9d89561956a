"""One shared switch for BLAS threading.

SLSQP (lift) and the banded solves (refine) make many tiny LAPACK calls; a multithreaded OpenBLAS
spends more time waking its threads than computing (figures:
``benchmarks/results/design_measurements.md``). Wrap those solver calls in :func:`single_blas_thread`.
"""

from __future__ import annotations

from threadpoolctl import ThreadpoolController, threadpool_info, threadpool_limits

_CONTROLLER: ThreadpoolController | None = None


def blas_description() -> str:
    """The loaded BLAS libraries with the CPU kernels they picked, e.g. ``"openblas 0.3.31
    SkylakeX"``, comma-separated and deduplicated; "" when none is found. OpenBLAS picks its
    kernels per CPU at run time, so one install on two machines can round differently."""
    seen = []
    for info in threadpool_info():  # a fresh scan, not the controller's: cv2 loads its own later
        if info.get("user_api") != "blas":
            continue
        text = " ".join(
            str(info[k]) for k in ("internal_api", "version", "architecture") if info.get(k)
        )
        if text not in seen:
            seen.append(text)
    return ", ".join(seen)


def single_blas_thread() -> threadpool_limits:
    """Context manager limiting BLAS/LAPACK to one thread in this process.

    The loaded libraries are found once per process (threadpoolctl scans every shared object on
    each plain ``threadpool_limits``, a few hundred microseconds per call: 4 % of the lift's time
    with one call per SLSQP solve); scipy.linalg is imported first so that both numpy's and
    scipy's BLAS are loaded when they are found.
    """
    global _CONTROLLER
    if _CONTROLLER is None:
        import scipy.linalg  # noqa: F401  (loads scipy's BLAS)

        _CONTROLLER = ThreadpoolController()
    return _CONTROLLER.limit(limits=1, user_api="blas")
