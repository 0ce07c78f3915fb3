"""Where batch work runs: in this process, in a pool of local processes, or on a Dask cluster.

The three pools share one small interface, so batch jobs and split blob detection are written
once: ``submit(fn, *args)`` returns a handle, ``wait_any(handles)`` blocks until at least one
is finished and returns ``(done, not_done)``, ``result(handle)`` returns the value or raises
the task's exception.

* :class:`InlinePool` runs each task in the calling process, lazily, when it is waited for
  (one worker; no pickling; easiest to debug).
* :class:`LocalPool` is a :class:`concurrent.futures.ProcessPoolExecutor` whose workers are
  started by a fork server preloaded with carapost (no fork of a process that has threads or
  an OpenCV thread pool running; cheap worker start).
* :class:`DaskPool` submits to ``dask.distributed.Client(address)``. Tasks are module-level
  functions of carapost, so every Dask worker needs carapost installed, and the take files
  must be reachable at the same paths (shared storage).

Functions and arguments given to a process or Dask pool must be picklable.
"""

from __future__ import annotations

import contextlib
from abc import ABC, abstractmethod
import multiprocessing
import os
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from typing import Any

__all__ = ["Pool", "InlinePool", "LocalPool", "DaskPool", "open_pool", "cpu_count", "limit_threads"]

#: Modules imported once by the fork server, before any worker starts (workers are forked from
#: it, so they start with these loaded). Includes the heavy modules carapost imports lazily on
#: first use (the blob detector's ``scipy.spatial``: 0.3 s per worker otherwise).
PRELOAD = ["carapost.ops.batch", "carapost.ops.split_detect", "carapost.core.blobs", "scipy.spatial",
           "scipy.optimize", "h5py", "threadpoolctl"]


@contextlib.contextmanager
def limit_threads(n: int = 1) -> Iterator[None]:
    """Limit OpenCV's and the BLAS library's own thread pools to ``n`` threads inside the block.

    Batch workers parallelise explicitly (processes x threads); the libraries' pools on top
    oversubscribe the cores. OpenBLAS in particular spins a second thread on the detector's
    small matrix products, doubling its CPU time for no gain (``docs/batch.md``).
    """
    import cv2

    old = cv2.getNumThreads()
    cv2.setNumThreads(max(1, int(n)))
    try:
        try:
            from threadpoolctl import threadpool_limits
        except ImportError:  # pragma: no cover - an install without threadpoolctl
            yield
        else:
            with threadpool_limits(limits=max(1, int(n)), user_api="blas"):
                yield
    finally:
        cv2.setNumThreads(old)


def cpu_count() -> int:
    """Cores this process may use (the affinity mask where the platform has one)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


class Pool(ABC):
    """The interface of the pools (see the module docstring)."""

    #: Tasks run in another process: their log records do not reach this process's handlers.
    remote: bool = True
    #: How many tasks run at once.
    workers: int = 1
    #: Shown in summaries: "inline", "processes" or the scheduler address.
    where: str = ""

    @abstractmethod
    def submit(self, fn: Callable[..., Any], /, *args: Any) -> Any:
        """Start ``fn(*args)``; returns a handle (a future)."""

    @abstractmethod
    def wait_any(self, handles: Iterable[Any]) -> tuple[list[Any], list[Any]]:
        """Block until at least one handle is done: ``(done, pending)``."""

    def result(self, handle: Any) -> Any:
        return handle.result()

    def cancel(self, handles: Iterable[Any]) -> None:
        for h in handles:
            h.cancel()

    def close(self) -> None:
        pass

    def __enter__(self) -> "Pool":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class _Lazy:
    """A task of :class:`InlinePool`: run when first waited for."""

    def __init__(self, fn: Callable[..., Any], args: tuple) -> None:
        self.fn, self.args = fn, args
        self.future: Future = Future()

    def run(self) -> None:
        if self.future.done():
            return
        try:
            self.future.set_result(self.fn(*self.args))
        except Exception as exc:  # the task's failure, re-raised by result()
            self.future.set_exception(exc)

    def result(self) -> Any:
        self.run()
        return self.future.result()

    def cancel(self) -> bool:
        return self.future.cancel()

    def cancelled(self) -> bool:
        return self.future.cancelled()


class InlinePool(Pool):
    """Run tasks one at a time in the calling process."""

    remote = False
    workers = 1
    where = "inline"

    def submit(self, fn: Callable[..., Any], /, *args: Any) -> _Lazy:
        return _Lazy(fn, args)

    def wait_any(self, handles: Iterable[Any]) -> tuple[list[Any], list[Any]]:
        hs = list(handles)
        done = [h for h in hs if h.future.done()]
        if not done and hs:
            hs[0].run()
            done = [hs[0]]
        return done, [h for h in hs if h not in done]


class LocalPool(Pool):
    """``workers`` processes on this machine (:class:`~concurrent.futures.ProcessPoolExecutor`)."""

    where = "processes"

    def __init__(self, workers: int) -> None:
        if workers < 1:
            raise ValueError(f"workers must be at least 1, got {workers}")
        methods = multiprocessing.get_all_start_methods()
        ctx = multiprocessing.get_context("forkserver" if "forkserver" in methods else "spawn")
        if ctx.get_start_method() == "forkserver":
            ctx.set_forkserver_preload(PRELOAD)
        self.workers = workers
        self._pool = ProcessPoolExecutor(max_workers=workers, mp_context=ctx)

    def submit(self, fn: Callable[..., Any], /, *args: Any) -> Future:
        return self._pool.submit(fn, *args)

    def wait_any(self, handles: Iterable[Any]) -> tuple[list[Any], list[Any]]:
        done, not_done = wait(list(handles), return_when=FIRST_COMPLETED)
        return list(done), list(not_done)

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)


class DaskPool(Pool):
    """Tasks on a Dask distributed cluster.

    Parameters
    ----------
    scheduler : str or distributed.Client
        The scheduler's address (``tcp://host:8786``) or a connected client (not closed by
        :meth:`close`).

    Raises
    ------
    ValueError
        If dask.distributed is not installed or the scheduler cannot be reached.
    """

    def __init__(self, scheduler: Any, *, timeout: float = 30.0) -> None:
        try:
            import distributed
        except ImportError:  # pragma: no cover - an install problem
            raise ValueError("--scheduler needs dask.distributed: pip install 'dask[distributed]'") from None
        self._distributed = distributed
        if isinstance(scheduler, distributed.Client):
            self._client, self._own = scheduler, False
        else:
            try:
                self._client = distributed.Client(str(scheduler), timeout=timeout, set_as_default=False)
            except (OSError, TimeoutError, ValueError) as exc:
                raise ValueError(f"cannot connect to the Dask scheduler {scheduler}: {exc}") from None
            self._own = True
        self.where = str(self._client.scheduler.address)
        self.workers = max(1, sum(self._client.nthreads().values()))

    def submit(self, fn: Callable[..., Any], /, *args: Any) -> Any:
        return self._client.submit(fn, *args, pure=False)

    def wait_any(self, handles: Iterable[Any]) -> tuple[list[Any], list[Any]]:
        hs = list(handles)
        with self._client.as_current():
            res = self._distributed.wait(hs, return_when="FIRST_COMPLETED")
        done = set(res.done)
        return [h for h in hs if h in done], [h for h in hs if h not in done]

    def close(self) -> None:
        if self._own:
            self._client.close()


def open_pool(workers: int = 1, scheduler: Any = None) -> Pool:
    """The pool for ``--workers N`` / ``--scheduler ADDRESS``.

    ``workers=1`` without a scheduler runs inline; more starts local processes.
    """
    if scheduler is not None:
        return DaskPool(scheduler)
    if workers < 1:
        raise ValueError(f"workers must be at least 1, got {workers}")
    return InlinePool() if workers == 1 else LocalPool(workers)
