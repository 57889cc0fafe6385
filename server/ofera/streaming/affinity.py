"""The CPUs the server runs on (the ``cpus`` setting, ``ofera serve --cpus``): Linux CPU affinity for every thread of
the process, set once at start.

A server next to its clients (a Unity app, a replay, a benchmark) on a small machine shares cores with them: the
kernel wakes the server's threads on the client's core (preempting it: a 300-byte bs took the benchmark client 0.56 ms
to send, 0.11 ms with the two on separate CPUs) and moves them between cores. Keeping them apart is the user's choice;
what it gains varies (benchmarks/README.md, round nine): on the 2-core VM of December 2026 one session with the
server on CPU 0 and its client on CPU 1 had e2e p99 1.3-3.4 ms lower than unpinned in one hour, the same in another.
"""

from __future__ import annotations

import os
import re
import sys

_ITEM = re.compile(r"^\s*(\d+)\s*(?:-\s*(\d+)\s*)?$")


def parse_cpus(text: str) -> frozenset[int]:
    """A CPU list as Linux writes it ("0", "2-3,6") -> the CPU numbers. ValueError naming the bad part."""
    cpus: set[int] = set()
    for part in text.split(","):
        m = _ITEM.match(part)
        if m is None:
            raise ValueError(f"not a CPU list (e.g. 0 or 2-3,6): {text!r} (at {part.strip()!r})")
        lo, hi = int(m.group(1)), int(m.group(2) or m.group(1))
        if hi < lo:
            raise ValueError(f"CPU range {part.strip()!r} runs backwards")
        cpus.update(range(lo, hi + 1))
    return frozenset(cpus)


def pin_process(cpus: frozenset[int]) -> frozenset[int]:
    """Run every thread of this process (those started so far, and through them those started later) on those of
    ``cpus`` the machine has and lets it use (its cpuset); numba's thread pool, if not started yet, then has at most
    that many threads. Returns the affinity now in force. ValueError if this OS has no CPU affinity or none of
    ``cpus`` can be used."""
    if not hasattr(os, "sched_setaffinity"):
        raise ValueError("the cpus setting needs Linux (os.sched_setaffinity)")
    try:
        os.sched_setaffinity(0, cpus)  # the kernel keeps those it has and allows; none of them: EINVAL
    except OSError as exc:
        raise ValueError(f"none of CPUs {sorted(cpus)} can be used by this process ({exc.strerror}; it may use "
                         f"{sorted(os.sched_getaffinity(0))} now)") from None
    pinned = frozenset(os.sched_getaffinity(0))
    for task in os.listdir("/proc/self/task"):
        try:
            os.sched_setaffinity(int(task), pinned)
        except ProcessLookupError:  # a thread that has just ended
            pass
    _limit_numba(len(pinned))
    return pinned


SPIN_COUNT = 10000
"""How long an idle numba (OpenMP) worker of the server spins before it sleeps, in libgomp's ``GOMP_SPINCOUNT`` units
(25-30 ns each on the Intel VM of 7 December 2026: 0.3 ms): long enough for the gap between a frame's two parallel
regions, not for the 13.9 ms between frames. libgomp's own default (300000: 7.4 ms after every region) kept a lone
session's worker spinning for half of every frame interval once two threads were all libgomp managed (a lone session
on the loop's thread): the server used 0.69 cores against 0.21, with the same e2e (four ABBA pairs, round twenty)."""


def bound_spinning() -> bool:
    """Set ``GOMP_SPINCOUNT`` to :data:`SPIN_COUNT` for this process unless the user set it or ``OMP_WAIT_POLICY``;
    libgomp reads it once, when numba's thread pool starts. Returns whether it was set (False too when the pool had
    already started)."""
    if "GOMP_SPINCOUNT" in os.environ or "OMP_WAIT_POLICY" in os.environ or _numba_pool_started():
        return False
    os.environ["GOMP_SPINCOUNT"] = str(SPIN_COUNT)
    return True


def _numba_pool_started() -> bool:
    """Whether numba's thread pool has started (its size and libgomp's settings are then fixed)."""
    if "numba" not in sys.modules:
        return False
    from numba.np.ufunc import parallel

    return bool(parallel._is_initialized)


def cpus_in_use() -> list[int] | None:
    """The CPUs this process may run on (its affinity), or None where the OS does not say (/healthz shows it)."""
    return sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None


def usable_cpus() -> int:
    """How many CPUs this process may run on."""
    cpus = cpus_in_use()
    return len(cpus) if cpus else os.cpu_count() or 1


def _limit_numba(count: int) -> None:
    """numba sizes its pool from the affinity when first imported; if it was imported before the pinning and its
    pool has not started, the pool is sized down here (a started pool keeps its threads: they share the CPUs)."""
    if "numba" not in sys.modules or _numba_pool_started():
        return
    import numba
    from numba.np.ufunc import parallel

    if numba.config.NUMBA_NUM_THREADS > count:
        # Both: numba's pool starts NUM_THREADS threads (read when numba.np.ufunc.parallel was imported), while the
        # parallel kernels size their per-thread work from the config. Set apart, a threaded frame wrote past its
        # buffers (a pinned server whose numba came in before the pinning crashed: "malloc(): unaligned tcache
        # chunk detected", round nineteen).
        numba.config.NUMBA_NUM_THREADS = parallel.NUM_THREADS = count
