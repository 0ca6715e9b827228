"""Run independent tasks on local processes (or a Dask cluster), in order, with progress.

Given a :class:`DaskExecutor`, the tasks go to a Dask cluster instead (each
task computes exactly what it computes locally: results are bit-identical
when the cluster's workers run their native libraries single-threaded, as
:func:`tools.batch.local_cluster` starts them). The executor is handed in by
the caller; nothing is read from a module global.

The pool is ``multiprocessing.Pool``, whose ``terminate`` stops the workers
at once on an error or an interrupt. It uses the ``spawn`` start method:
``fork`` deadlocks once the parent has used OpenMP (rawpy) or OpenCV threads
(docs/method.md section 14). Workers run their native libraries single-threaded, so two
workers use the two cores without oversubscription and every task computes
exactly what it computes in-process.
This module imports nothing heavy at the top: the worker initializer must run
before numpy loads its BLAS.
"""

from __future__ import annotations

import contextlib
import os
from dataclasses import dataclass
from typing import Callable, Iterable, Iterator, Sequence, TypeVar

T = TypeVar("T")
R = TypeVar("R")

_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "OPENCV_FOR_THREADS_NUM")


def _init_worker() -> None:
    import signal

    import cv2

    for var in _THREAD_VARS:
        os.environ[var] = "1"
    threadpool_limits_loaded(1)  # BLAS and OpenMP, whatever the environment the pool started from
    cv2.setNumThreads(1)  # two workers already fill the two cores
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the whole group: the parent ends the work


@contextlib.contextmanager
def single_threaded_math() -> Iterator[None]:
    """Within this block BLAS and OpenMP run one thread (threadpoolctl), as in the workers.

    A threaded dot product sums in an order that depends on the thread count, so a solve here
    would differ in the last bits from one in a worker process or on a Dask worker (measured: 78
    pixels' confidence off by 1 ulp at 320x240); and the solver's many small products are slower
    threaded (a 320x240x8 estimate called from Python took 57-71 s of CPU time with threaded BLAS
    against 2.3 s single-threaded). OpenCV's own threads change no result and stay on.
    """
    with threadpool_limits_loaded(1):
        yield


def threadpool_limits_loaded(limits: int):
    """``threadpoolctl.threadpool_limits(limits)`` once every library that brings its own BLAS is
    loaded: the limit reaches only those loaded when it is set, and NumPy, SciPy and OpenCV each
    ship their own OpenBLAS (three seen here)."""
    import cv2  # noqa: F401 (loads its BLAS)
    import scipy.linalg  # noqa: F401
    import scipy.sparse.linalg  # noqa: F401
    from threadpoolctl import threadpool_limits

    return threadpool_limits(limits=limits)


def map_ordered(
    fn: Callable[[T], R],
    tasks: Sequence[T],
    *,
    workers: int = 2,
    progress: Callable[[int], None] | None = None,
    executor: DaskExecutor | None = None,
) -> list[R]:
    """``[fn(t) for t in tasks]``, on ``workers`` processes when more than one, or on ``executor``.

    ``fn`` must be a module-level function; results come back in task order.
    ``progress(1)`` is called as each task finishes.
    """
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    if executor is not None:
        return executor.map(fn, tasks, progress)
    return list(imap_ordered(fn, tasks, workers=workers, progress=progress))


def imap_ordered(
    fn: Callable[[T], R],
    tasks: Sequence[T],
    *,
    workers: int = 2,
    progress: Callable[[int], None] | None = None,
) -> Iterator[R]:
    """:func:`map_ordered`'s results on local processes, yielded in task order as each comes: a
    caller that folds them in holds one at a time. The workers stop when the results are all
    taken, or at once when the caller stops taking them (or fails)."""
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    if workers == 1 or len(tasks) <= 1:
        yield from _serial(fn, tasks, progress)
        return
    import multiprocessing as mp

    with single_threaded_children():
        pool = mp.get_context("spawn").Pool(min(workers, len(tasks)), initializer=_init_worker)
    try:
        for result in pool.imap(fn, tasks):  # in task order, as each completes in turn
            if progress:
                progress(1)
            yield result
        pool.close()
        pool.join()
    except BaseException:  # a failed task, Ctrl-C, SIGTERM, or the results left (GeneratorExit): stop the workers now
        pool.terminate()
        pool.join()
        raise


@contextlib.contextmanager
def single_threaded_children() -> Iterator[None]:
    """Within this block, processes started inherit single-threaded native libraries (BLAS, OpenMP,
    OpenCV); this process's environment is restored after."""
    saved = {var: os.environ.get(var) for var in _THREAD_VARS}
    os.environ.update({var: "1" for var in _THREAD_VARS})
    try:
        yield
    finally:
        for var, value in saved.items():
            if value is None:
                os.environ.pop(var, None)
            else:
                os.environ[var] = value


def _serial(fn: Callable[[T], R], tasks: Iterable[T], progress) -> Iterable[R]:
    for task in tasks:
        result = fn(task)
        if progress:
            progress(1)
        yield result


@dataclass(frozen=True)
class DaskExecutor:
    """Run :func:`map_ordered`'s tasks on a Dask cluster instead of local processes: hand it to
    ``pipeline.estimate(..., executor=...)`` (``estimate --scheduler``). Each task computes exactly
    what it computes locally, so results are bit-identical when the cluster's workers run their
    native libraries single-threaded (as :func:`tools.batch.local_cluster` starts them)."""

    client: object

    def map(self, fn, tasks, progress=None) -> list:
        return _on_dask(self.client, fn, tasks, progress)


def _on_dask(client, fn, tasks, progress) -> list:
    """``[fn(t) for t in tasks]`` on a Dask cluster, in task order; the futures are cancelled on any error."""
    futures = client.map(fn, list(tasks), pure=False)
    try:
        results = []
        for future in futures:
            results.append(future.result())
            if progress:
                progress(1)
        return results
    except BaseException:
        client.cancel(futures)
        raise
