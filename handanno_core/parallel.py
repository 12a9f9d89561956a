"""Back-ends for running many independent jobs: this process, local processes, a Dask cluster.

:class:`Runner` maps a function over jobs in order and keeps its pool (or Dask client) open
across calls, so repeated rounds (the lift's bone-length rounds: a map over references, then a
reduction in the caller) pay the start-up once. ``share(obj)`` puts a large argument on the
cluster once (``Client.scatter``) and returns a handle that jobs may carry instead of the object;
locally it is the object itself. :meth:`Runner.each` hands every result to a callback as soon as it
is done (any order): the propagation's and the refinement pieces' back-ends.

Local pools start their processes by ``fresh_processes=True``: forkserver (spawn where there is
none), not fork, so a caller with threads (the app's background jobs) is safe and workers see
only what they import; ``False`` forks (cheaper start, the lift's rounds).

A Dask scheduler is given as ``"tcp://HOST:PORT"`` (or as a ``dask.distributed.Client``, used and
left open). Workers must import this package (same version) and see the session's files under the
same paths: crops and depth maps are read by path, a shared filesystem is assumed.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

__all__ = ["Runner", "dask_client", "frame_ranges"]


def frame_ranges(
    n: int, workers: int, *, breaks=None, per_worker: int = 4
) -> list[tuple[int, int]]:
    """Consecutive ranges ``[(a, b), ...]`` covering frames ``0..n-1``, about ``n / (per_worker *
    workers)`` frames each (a few jobs per process balance uneven ones). With ``breaks`` (sequence
    break frames, possibly empty) every range is a run of whole segments: ranges start only at 0
    or a break (a segment longer than the target is one range)."""
    target = max(1, -(-n // max(1, per_worker * max(1, int(workers)))))
    if breaks is None:
        starts = list(range(0, n, target))
    else:
        cuts = sorted({int(b) for b in breaks if 0 < int(b) < n})
        starts = [0]
        for c in cuts:
            if c - starts[-1] >= target:
                starts.append(c)
    if n <= 0:
        return []
    return list(zip(starts, [*starts[1:], n], strict=True))


@contextmanager
def dask_client(scheduler) -> Iterator[Any]:
    """A ``dask.distributed.Client`` for ``scheduler`` (closed on exit unless it was given)."""
    try:
        from dask.distributed import Client
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError(
            "scheduler= needs dask.distributed: pip install 'handanno[distributed]'"
        ) from exc
    own = not isinstance(scheduler, Client)
    client = Client(scheduler) if own else scheduler
    try:
        yield client
    finally:
        if own:
            client.close()


class Runner:
    """``with Runner(workers, scheduler) as r: r.map(fn, jobs)`` -> results in job order."""

    def __init__(self, workers: int = 1, scheduler=None, *, fresh_processes: bool = False):
        self.workers = max(1, int(workers))
        self.scheduler = scheduler
        self.fresh_processes = fresh_processes
        self._pool = None
        self._client = None
        self._client_cm = None

    def __enter__(self) -> Runner:
        if self.scheduler is not None:
            self._client_cm = dask_client(self.scheduler)
            self._client = self._client_cm.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None
        if self._client_cm is not None:
            self._client_cm.__exit__(*exc)
            self._client_cm = self._client = None

    def share(self, obj, *, broadcast: bool = False):
        """A handle for ``obj`` that jobs can carry (scattered once on a cluster, to every worker
        with ``broadcast``)."""
        if self._client is None:
            return obj
        if broadcast:
            return self._client.scatter(obj, broadcast=True)
        return self._client.scatter(obj, hash=False)

    def _local_pool(self):
        if self._pool is None:
            from concurrent.futures import ProcessPoolExecutor

            context = None
            if self.fresh_processes:
                import multiprocessing as mp

                method = "forkserver" if "forkserver" in mp.get_all_start_methods() else "spawn"
                context = mp.get_context(method)
            self._pool = ProcessPoolExecutor(max_workers=self.workers, mp_context=context)
        return self._pool

    def each(self, fn: Callable, jobs: list, collect: Callable[[Any], None], *args) -> None:
        """``collect(fn(*args, job))`` for every job, as each finishes (any order); ``args`` (e.g.
        :meth:`share` handles) go to every call. In this process when ``workers == 1`` and there
        is no scheduler."""
        if self._client is not None:
            from dask.distributed import as_completed

            futures = [self._client.submit(fn, *args, job, pure=False) for job in jobs]
            for fut in as_completed(futures):
                collect(fut.result())
        elif self.workers > 1:
            from concurrent.futures import as_completed

            pool = self._local_pool()
            for fut in as_completed([pool.submit(fn, *args, job) for job in jobs]):
                collect(fut.result())
        else:
            for job in jobs:
                collect(fn(*args, job))

    def map(
        self, fn: Callable, jobs: list, progress: Callable[[int, int], None] | None = None
    ) -> list:
        """``[fn(job) for job in jobs]``, on the back-end; ``progress(done, total)`` per job."""
        total = len(jobs)
        out: list = [None] * total
        if self._client is not None:
            from dask.distributed import as_completed

            futures = [self._client.submit(fn, job, pure=False) for job in jobs]
            index = {f.key: i for i, f in enumerate(futures)}
            for done, fut in enumerate(as_completed(futures), start=1):
                out[index[fut.key]] = fut.result()
                if progress is not None:
                    progress(done, total)
            return out
        if self.workers > 1 and total > 1:
            chunk = max(1, total // (4 * self.workers))
            for i, r in enumerate(self._local_pool().map(fn, jobs, chunksize=chunk)):
                out[i] = r
                if progress is not None:
                    progress(i + 1, total)
            return out
        for i, job in enumerate(jobs):
            out[i] = fn(job)
            if progress is not None:
                progress(i + 1, total)
        return out
