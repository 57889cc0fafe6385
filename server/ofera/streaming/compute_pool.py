"""The server's compute threads: a thread pool whose hand-off to a thread and back costs what it must, and no more.

``loop.run_in_executor(ThreadPoolExecutor)`` moves a frame to a thread and back through a work item, a
``concurrent.futures.Future`` (a Condition, an RLock), its callbacks, ``wrap_future`` and the loop's bookkeeping: on
the 2-vCPU VM of December 2026, after a 13.9 ms idle gap (a 72 Hz frame's), 155-170 us to the thread and 85-155 us
back (uvloop; benchmarks/README.md, round twelve). :class:`ComputePool` gives each thread its own lock to wake on and
a job slot, keeps idle threads on a stack (the last one used, whose caches are warm, goes first) and settles an
asyncio future straight from the thread with one ``call_soon_threadsafe``: 75-80 us there and 45-80 back, the same
machine and idle gap. It is also a ``concurrent.futures.Executor`` (``submit``, ``run_in_executor``) for everything
else the server runs on its threads (loading avatars, preparing wires).

    pool = ComputePool(2)
    frame = await pool.run(compute, pending)    # the hot path: an asyncio future, settled on the loop
    await loop.run_in_executor(pool, load)      # anything else: the Executor interface
"""

from __future__ import annotations

import asyncio
import functools
import threading
from collections import deque
from collections.abc import Callable
from concurrent.futures import CancelledError, Executor, Future
from typing import Any

_STOP = object()  # a worker's job slot when the pool shuts down


class _Worker:
    """One thread: blocks on its own lock until the pool hands it a job (``job``), then takes queued jobs until none
    is left and goes back on the pool's idle stack."""

    def __init__(self, pool: ComputePool, name: str) -> None:
        self.pool = pool
        self.wake = threading.Lock()
        self.wake.acquire()  # held: the thread blocks on it until a job is handed over
        self.job: Any = None
        self.thread = threading.Thread(target=self._run, name=name, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        pool = self.pool
        while True:
            self.wake.acquire()
            job = self.job
            while job is not None and job is not _STOP:
                _do(*job)  # a call of its own: nothing of a finished job stays referenced by an idle thread
                job = pool._next(self)
            if job is _STOP:
                return


def _do(fn: Callable[..., Any], args: tuple, settle: Callable[[Any, BaseException | None], None]) -> None:
    try:
        result = fn(*args)
    except BaseException as exc:  # noqa: BLE001 - handed to whoever awaits the job
        settle(None, exc)
    else:
        settle(result, None)


class ComputePool(Executor):
    """``threads`` daemon threads running jobs: :meth:`run` from the event loop (an asyncio future) or :meth:`submit`
    from anywhere (a concurrent future). Jobs start in the order given; a job waits only while every thread is
    busy."""

    def __init__(self, threads: int, name: str = "ofera-compute") -> None:
        if threads < 1:
            raise ValueError(f"a compute pool needs at least one thread, not {threads}")
        self._mutex = threading.Lock()
        self._queue: deque[tuple] = deque()
        self._closed = False
        self._workers = [_Worker(self, f"{name}_{k}") for k in range(threads)]
        self._idle = list(reversed(self._workers))  # a stack: the top is the next to work

    @property
    def threads(self) -> int:
        return len(self._workers)

    def run(self, fn: Callable[..., Any], *args: Any) -> asyncio.Future:
        """``fn(*args)`` on a pool thread, as a future of the running loop (call from the loop's thread)."""
        loop = asyncio.get_running_loop()
        fut = loop.create_future()

        def settle(result: Any, exc: BaseException | None) -> None:
            try:
                loop.call_soon_threadsafe(_settle, fut, result, exc)
            except RuntimeError:  # the loop is closed: nobody is waiting any more
                pass

        self._give((fn, args, settle))
        return fut

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> Future:
        """``fn(*args, **kwargs)`` on a pool thread, as a concurrent future (the Executor interface)."""
        fut: Future = Future()

        def settle(result: Any, exc: BaseException | None) -> None:
            if not fut.set_running_or_notify_cancel():
                return
            if exc is None:
                fut.set_result(result)
            else:
                fut.set_exception(exc)

        self._give((functools.partial(fn, **kwargs) if kwargs else fn, args, settle))
        return fut

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        """No more jobs; the threads end once their queued jobs are done (``cancel_futures``: queued jobs are
        cancelled instead). ``wait``: return once every thread has ended."""
        with self._mutex:
            if self._closed:
                dropped: list[tuple] = []
            else:
                self._closed = True
                dropped = list(self._queue) if cancel_futures else []
                if cancel_futures:
                    self._queue.clear()
            idle, self._idle = self._idle, []
        for _, _, settle in dropped:
            settle(None, CancelledError())
        for w in idle:
            w.job = _STOP
            w.wake.release()
        if wait:
            for w in self._workers:
                if w.thread is not threading.current_thread():
                    w.thread.join()

    def _give(self, job: tuple) -> None:
        with self._mutex:
            if self._closed:
                raise RuntimeError("cannot schedule new jobs after shutdown")
            if not self._idle:
                self._queue.append(job)
                return
            w = self._idle.pop()
        w.job = job
        w.wake.release()

    def _next(self, worker: _Worker) -> Any:
        """The next queued job for ``worker``, else None (it goes idle) or _STOP (the pool is shut down)."""
        with self._mutex:
            if self._queue:
                return self._queue.popleft()
            if self._closed:
                return _STOP
            worker.job = None
            self._idle.append(worker)
            return None


def _settle(fut: asyncio.Future, result: Any, exc: BaseException | None) -> None:
    """On the loop: the job's outcome into its future, unless whoever awaited it gave up (cancelled)."""
    if fut.cancelled():
        return
    if exc is None:
        fut.set_result(result)
    else:
        fut.set_exception(exc)


def offload(executor: Executor, fn: Callable[..., Any], *args: Any) -> asyncio.Future:
    """``fn(*args)`` on ``executor``'s threads as an asyncio future: a :class:`ComputePool`'s own hand-off, else
    ``run_in_executor`` (any other Executor: tests pass ThreadPoolExecutors)."""
    if isinstance(executor, ComputePool):
        return executor.run(fn, *args)
    return asyncio.get_running_loop().run_in_executor(executor, fn, *args)
