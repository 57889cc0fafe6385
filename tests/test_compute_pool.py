"""The server's compute threads (`streaming.compute_pool`): jobs from the loop (`run`) and from anywhere (`submit`,
`run_in_executor`) run on the pool's threads, queue while every thread is busy and start in the order given, carry
their exceptions back, and a shutdown cancels or finishes what is queued."""

from __future__ import annotations

import asyncio
import threading
import time
from concurrent.futures import CancelledError, ThreadPoolExecutor

import pytest
from ofera.streaming.compute_pool import ComputePool, offload

WAIT = 10.0  # seconds a step may take before the test calls it hung (never a performance claim)


def test_run_gives_the_result_from_a_pool_thread() -> None:
    pool = ComputePool(2, name="t-pool")

    async def main() -> tuple[str, int]:
        return await asyncio.wait_for(pool.run(lambda x: (threading.current_thread().name, x * 2), 21), WAIT)

    name, value = asyncio.run(main())
    assert value == 42 and name.startswith("t-pool_") and name != threading.current_thread().name
    pool.shutdown()


def test_exceptions_reach_whoever_awaits() -> None:
    pool = ComputePool(1)

    def boom() -> None:
        raise ValueError("bad frame")

    async def main() -> None:
        with pytest.raises(ValueError, match="bad frame"):
            await asyncio.wait_for(pool.run(boom), WAIT)
        with pytest.raises(ValueError, match="bad frame"):
            await asyncio.wait_for(asyncio.get_running_loop().run_in_executor(pool, boom), WAIT)
        assert await asyncio.wait_for(pool.run(lambda: 7), WAIT) == 7  # the thread goes on

    asyncio.run(main())
    pool.shutdown()


def test_jobs_queue_while_every_thread_is_busy_and_start_in_order() -> None:
    pool = ComputePool(2)
    gate = threading.Event()
    started: list[int] = []
    lock = threading.Lock()

    def job(k: int) -> int:
        with lock:
            started.append(k)
        if k < 2:
            assert gate.wait(WAIT)  # the first two hold both threads
        return k

    async def main() -> list[int]:
        futs = [pool.run(job, k) for k in range(8)]
        await asyncio.sleep(0.05)
        assert sorted(started) == [0, 1]  # the rest wait in the queue
        gate.set()
        return await asyncio.wait_for(asyncio.gather(*futs), WAIT)

    assert asyncio.run(main()) == list(range(8))
    pool.shutdown()

    one = ComputePool(1)  # one thread: the queue's order is the order they run in
    order: list[int] = []
    futs = [one.submit(order.append, k) for k in range(20)]
    for f in futs:
        f.result(WAIT)
    assert order == list(range(20))
    one.shutdown()


def test_submit_runs_anywhere_with_keyword_arguments() -> None:
    pool = ComputePool(3)
    results = [pool.submit(lambda a, b=0: a + b, k, b=10) for k in range(20)]
    assert [f.result(WAIT) for f in results] == [k + 10 for k in range(20)]
    with ThreadPoolExecutor(4) as other:  # from other threads at once
        nested = list(other.map(lambda k: pool.submit(pow, k, 2).result(WAIT), range(50)))
    assert nested == [k * k for k in range(50)]
    pool.shutdown()


def test_a_cancelled_await_is_not_settled_again() -> None:
    pool = ComputePool(1)
    gate = threading.Event()

    async def main() -> int:
        fut = pool.run(lambda: gate.wait(WAIT))
        fut.cancel()
        gate.set()
        await asyncio.sleep(0.05)  # the thread's settling finds the future cancelled: no InvalidStateError
        return await asyncio.wait_for(pool.run(lambda: 5), WAIT)

    assert asyncio.run(main()) == 5
    pool.shutdown()


def test_shutdown_finishes_or_cancels_what_is_queued_and_refuses_more() -> None:
    pool = ComputePool(1)
    gate = threading.Event()
    first = pool.submit(gate.wait, WAIT)
    queued = pool.submit(lambda: "ran")
    threading.Timer(0.05, gate.set).start()
    pool.shutdown(wait=True)
    assert first.result(0) is True and queued.result(0) == "ran"
    with pytest.raises(RuntimeError, match="after shutdown"):
        pool.submit(lambda: None)

    pool = ComputePool(1)
    gate.clear()
    busy = pool.submit(gate.wait, WAIT)
    dropped = pool.submit(lambda: "never")
    pool.shutdown(wait=False, cancel_futures=True)
    gate.set()
    assert busy.result(WAIT) is True
    with pytest.raises(CancelledError):
        dropped.result(WAIT)
    deadline = time.monotonic() + WAIT
    while any(w.thread.is_alive() for w in pool._workers) and time.monotonic() < deadline:
        time.sleep(0.01)
    assert not any(w.thread.is_alive() for w in pool._workers)


def test_offload_takes_any_executor() -> None:
    async def main() -> tuple[int, int]:
        with ThreadPoolExecutor(1) as ex:
            a = await offload(ex, abs, -3)
        pool = ComputePool(1)
        b = await offload(pool, abs, -4)
        pool.shutdown()
        return a, b

    assert asyncio.run(main()) == (3, 4)


def test_a_pool_needs_a_thread() -> None:
    with pytest.raises(ValueError, match="at least one thread"):
        ComputePool(0)
